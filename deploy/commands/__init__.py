"""One module per group of ``slcp`` commands: each adds its commands' parsers and names their handlers
(``HANDLERS``); :mod:`deploy.cli` puts them together."""

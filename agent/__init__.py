"""slcp vehicle agent: the pure navigation core (agent.nav) under an asyncio shell."""

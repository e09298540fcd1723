"""The vehicle layer: profiles of vehicle types (installation and sensor models, :mod:`.profile`)."""

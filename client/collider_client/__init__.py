"""Client side of the collider service: numpy + msgpack + httpx, no torch."""

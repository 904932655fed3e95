"""The reference Verlet cloth simulator behind ``collider simulate SCENE`` (numpy only)."""

"""Subcommands of the ``collider`` CLI, one module per group (see :mod:`collider_cli.main`)."""

"""The client package stays light and exports what it documents."""

import subprocess
import sys

import collider_client


def test_import_does_not_load_torch_or_the_engine():
    code = ("import sys, collider_client, collider_client.response, collider_client.sim.scene, "
            "collider_client.sim.simulator; "
            "bad = [m for m in ('torch', 'collider_server') if m in sys.modules]; print(bad)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_all_is_complete_and_importable():
    public = {name for name in dir(collider_client) if not name.startswith("_")}
    # Submodules are reachable as attributes but are not API members.
    modules = {"response", "physics", "placement", "wire", "sim", "adapters"}
    assert public - modules - set(collider_client.__all__) == set()
    for name in collider_client.__all__:
        assert hasattr(collider_client, name), name


def test_no_exported_name_shadows_a_builtin():
    """``from collider_client import *`` leaves Python's own names alone (the SDK's timeout is
    ``RequestTimeoutError``, not ``TimeoutError``)."""
    import builtins

    assert [name for name in collider_client.__all__ if hasattr(builtins, name)] == []


def test_exception_tree_has_one_root():
    for name in collider_client.__all__:
        obj = getattr(collider_client, name)
        if isinstance(obj, type) and issubclass(obj, Exception):
            assert issubclass(obj, collider_client.ColliderError), name

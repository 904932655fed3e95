"""The latest values a collider keeps per pose or time (:mod:`collider_server.engine.kept`)."""

from collider_server.engine.kept import Kept


def test_the_latest_keep_values_are_kept_and_built_once():
    kept = Kept(2)
    built = []

    def build(key):
        built.append(key)
        return key * 10

    assert [kept.get(k, lambda k=k: build(k)) for k in (1, 2, 1, 3, 1, 2)] == [10, 20, 10, 30, 10, 20]
    # 1 asked again before 3 came, so 2 was the oldest and left; then 2 was built again.
    assert built == [1, 2, 3, 2] and len(kept) == 2
    kept.clear()
    assert len(kept) == 0 and kept.get(1, lambda: "again") == "again"

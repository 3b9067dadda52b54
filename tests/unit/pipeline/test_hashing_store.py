from __future__ import annotations

import hashlib
import os

from pipeline.hashing import DigestCache, canonical_json, record_key
from pipeline.store import ArtifactStore


def test_record_key_ignores_dict_order_but_not_values():
    assert record_key({"a": 1, "b": [1, 2]}) == record_key({"b": [1, 2], "a": 1})
    assert record_key({"a": 1}) != record_key({"a": 2})
    assert canonical_json({"b": 1, "a": 2}) == '{"a":2,"b":1}'


def test_digest_cache_hashes_once_and_notices_changes(tmp_path):
    f = tmp_path / "x.raw"
    f.write_bytes(b"hello")
    cache = DigestCache(tmp_path / "digests.json")
    assert cache.digest(f)["sha256"] == hashlib.sha256(b"hello").hexdigest()
    cache.save()
    again = DigestCache(tmp_path / "digests.json")
    again.digest(f)
    assert (again.hashed, again.reused) == (0, 1)
    f.write_bytes(b"hello, changed")
    os.utime(f, ns=(1, 1))
    assert again.digest(f)["sha256"] == hashlib.sha256(b"hello, changed").hexdigest()
    assert again.hashed == 1


def test_store_commit_is_all_or_nothing(tmp_path):
    store = ArtifactStore(tmp_path)
    key = "ab" * 32
    tmp = store.begin("decode", "A0000", key)
    (tmp / "out.txt").write_text("partial")
    assert not store.is_complete("decode", "A0000", key)  # a crash here leaves only .tmp-*
    store.discard("decode", "A0000", key)
    assert not tmp.exists()
    tmp = store.begin("decode", "A0000", key)
    (tmp / "out.txt").write_text("done")
    final = store.commit("decode", "A0000", key, {"r": 1}, {"s": 2}, 0.5)
    assert store.is_complete("decode", "A0000", key) and (final / "out.txt").read_text() == "done"
    assert store.latest_record("decode", "A0000")["key"] == key
    assert not tmp.exists()


def test_sweep_pointer_temps_removes_what_a_killed_writer_left_and_nothing_else(tmp_path):
    store = ArtifactStore(tmp_path)
    key = "cd" * 32
    store.begin("decode", "A0000", key)
    store.commit("decode", "A0000", key, {"r": 1}, {}, 0.1)
    folder = tmp_path / "decode" / "A0000"
    # a worker killed between writing its pointer and renaming it into place
    stale = [folder / ".latest.424242.tmp", folder / ".failed.424242.tmp"]
    for path in stale:
        path.write_text("{}")
    other = tmp_path / "decode" / "A0001"
    other.mkdir()
    (other / ".latest.7.tmp").write_text("{}")
    removed = store.sweep_pointer_temps([("decode", "A0000"), ("decode", "A0000"), ("photometric", "A0000")])
    assert removed == stale
    assert not any(p.exists() for p in stale)
    assert (other / ".latest.7.tmp").exists()  # a scope not named is left alone
    assert store.latest_record("decode", "A0000")["key"] == key and store.is_complete("decode", "A0000", key)
    assert store.sweep_pointer_temps([("decode", "A0000")]) == []

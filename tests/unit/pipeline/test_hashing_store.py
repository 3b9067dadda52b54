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

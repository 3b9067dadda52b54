"""pipeline.claims: one process claims a result, the others see the claim and whether its process is gone."""
from __future__ import annotations

import os
import time

from pipeline.claims import await_or_claim, claim_is_stale, try_claim


def test_a_claim_is_taken_once_and_holds_the_pid(tmp_path):
    claim = tmp_path / "result.claim"
    assert try_claim(claim)
    assert claim.read_text() == str(os.getpid())
    assert not try_claim(claim)  # held: a second claim fails, whoever asks
    claim.unlink()
    assert try_claim(claim)


def test_stale_when_the_process_is_gone_or_the_claim_is_old(tmp_path):
    claim = tmp_path / "result.claim"
    claim.write_text(str(os.getpid()))
    assert not claim_is_stale(claim, 60.0)  # a live process
    old = time.time() - 120
    os.utime(claim, (old, old))
    assert claim_is_stale(claim, 60.0)  # older than the limit, even if its process lives
    claim.write_text("999999999")
    assert claim_is_stale(claim, 60.0)  # no such process
    claim.write_text("")
    assert not claim_is_stale(claim, 60.0)  # being written: look again
    claim.unlink()
    assert not claim_is_stale(claim, 60.0)  # just removed: look again


def test_await_or_claim_returns_the_stored_result_or_the_claim(tmp_path):
    claim = tmp_path / "result.claim"
    assert await_or_claim(lambda: 7, claim, 60.0) == (7, False) and not claim.exists()
    assert await_or_claim(lambda: None, claim, 60.0) == (None, True)  # ours to produce
    assert claim.read_text() == str(os.getpid())
    assert await_or_claim(lambda: None, claim, 60.0, wait=False) == (None, False)  # a live holder
    answers = iter([None, 5])  # stored between the look and the claim: the claim is given back
    claim.write_text("999999999")  # and a dead holder's claim is taken over first
    assert await_or_claim(lambda: next(answers), claim, 60.0) == (5, False) and not claim.exists()

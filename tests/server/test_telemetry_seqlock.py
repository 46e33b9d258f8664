"""The telemetry ring's seqlock: a reader never gets a row that was half written or rewritten while
it copied it, with the loop's own kernel (``rings.account``) writing in another thread at full
speed (compiled, without the GIL) while this one reads, the ring lapping the reader again and
again."""
from __future__ import annotations

import threading

import numpy as np
from numba import njit

from hapticproxy.server import control as ctl
from hapticproxy.server.rings import account
from hapticproxy.server.shm import TEL_DTYPE, SharedState


@njit(nogil=True, cache=True)
def _write_rows(sh_tel, head, hist_late, hist_step, stat, cs, cnt, dev, cmd, n):
    """n telemetry rows through ``account``; every field a row can hold is its number k
    (``t_s`` k ns, ``cmd`` k), so a row mixing two writes shows it."""
    for _ in range(n):
        k = head[0]
        for j in range(6):
            cmd[j] = float(k)
        account(sh_tel, head, hist_late, hist_step, stat, 1000, 0, 0, k, 1.0, k, cs, cnt, dev, cmd)


def _consistent(rows) -> bool:
    k = rows["seq"]
    return bool(np.all(np.round(rows["t_s"] * 1e9) == k) and np.all(rows["updates"] == k)
                and np.all(rows["cmd"] == k[:, None]))


def test_a_reader_never_gets_a_torn_row():
    sh = SharedState.local(8)  # a tiny ring: the writer laps the reader all the time
    cs, cnt, dev, cmd = np.zeros(ctl.NCS), np.zeros(19, dtype=np.int64), np.zeros(20), np.zeros(6)
    args = (sh.tel, sh.head, sh.hist_late, sh.hist_step, sh.stat, cs, cnt, dev, cmd)
    _write_rows(*args, 10)
    done = threading.Event()

    def writer():
        while not done.is_set():
            _write_rows(*args, 200_000)

    t = threading.Thread(target=writer)
    t.start()
    got = 0
    try:
        for _ in range(20_000):
            head = int(sh.head[0])
            rows = sh.rows(max(0, head - 8), head)
            assert _consistent(rows), rows
            got += len(rows)
    finally:
        done.set()
        t.join()
    assert got > 0
    assert sh.torn_rows > 0  # the writer did rewrite rows under the reader: the check was exercised


def test_a_row_being_written_is_dropped_and_counted():
    sh = SharedState.local(4)
    cs, cnt, dev, cmd = np.zeros(ctl.NCS), np.zeros(19, dtype=np.int64), np.zeros(20), np.zeros(6)
    _write_rows(sh.tel, sh.head, sh.hist_late, sh.hist_step, sh.stat, cs, cnt, dev, cmd, 3)
    assert list(sh.rows(0, 3)["seq"]) == [0.0, 1.0, 2.0]
    sh.tel[1]["seq"] = -1.0  # the loop is writing row 1 (a lapped writer would be on row 5)
    assert list(sh.rows(0, 3)["seq"]) == [0.0, 2.0] and sh.torn_rows == 1
    assert sh.latest_row()["seq"] == 2.0
    assert sh.tel.dtype == TEL_DTYPE

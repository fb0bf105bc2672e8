"""The process `registration.BackgroundFitter` refits the Instrument SDF in (Stage 1, eqs. 1-4).

A fit is Python-heavy torch work: on a thread of the tracker's process it would hold the interpreter lock for much
of each Adam step, and the tracker's own Python-heavy steps (the posture graph) would wait on it. In a process of
its own it only shares the cores. Run as ``python -m surgtrack.sdf_worker READ_FD WRITE_FD``; it reads requests
from READ_FD and writes results to WRITE_FD, both pickled through `multiprocessing.connection.Connection`:

- first request: ``(state, iterations, num_threads)``, the field's `InstrumentSDF.state_dict` to start from, the
  Adam steps of a warm-started refit (None: the field's ``cfg.iterations``) and torch's thread count (None: its
  default);
- then one request per fit, a list of `tsdf.View`; the answer is ``(state, refined_poses, last_losses, report,
  None)`` or, when the fit failed, ``(None, None, None, None, error)`` (`InstrumentSDF.refit`: the first fit
  of an unfitted field runs ``cfg.iterations``; until the field converges, a fit goes on with the same views for
  up to ``cfg.converge_rounds`` more).

It exits when its input closes or when it is terminated; a fit in progress is then dropped. It ignores Ctrl-C,
which the terminal sends to the tracker and the worker alike: the tracker stops it. It runs at the lowest CPU
priority (nice 19 where the system has nice): a core the tracker wants is the tracker's, and the fit takes what is
left.
"""

from __future__ import annotations

import os
import signal
import sys
from multiprocessing.connection import Connection

import torch

from .registration import InstrumentSDF


def serve(conn_in: Connection, conn_out: Connection) -> None:
    """Fit each request from ``conn_in``, warm-started from the last fit, and answer on ``conn_out``."""
    state, iterations, num_threads = conn_in.recv()
    if num_threads is not None:
        torch.set_num_threads(int(num_threads))
    field = InstrumentSDF.from_state_dict(state)
    while True:
        try:
            views = conn_in.recv()
        except EOFError:
            return
        try:
            work = field.copy()
            report = work.refit(views, iterations, work.cfg.converge_rounds)
            field = work
            answer = (work.state_dict(), work.refined_poses, work.last_losses, report, None)
        except Exception as exc:  # noqa: BLE001 - sent back as the fitter's error; the process keeps serving
            answer = (None, None, None, None, RuntimeError(f"SDF fit failed: {type(exc).__name__}: {exc}"))
        conn_out.send(answer)


if __name__ == "__main__":
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if hasattr(os, "nice"):
        os.nice(19)
    serve(Connection(int(sys.argv[1]), writable=False), Connection(int(sys.argv[2]), readable=False))

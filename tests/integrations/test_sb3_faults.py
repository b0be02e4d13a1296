"""SharedPolicyVecEnv's worker faults: a dead, failing or stopped worker is named promptly, close() leaves no
process behind, workers ignore SIGINT and end with their learner."""

from __future__ import annotations

import functools
import multiprocessing
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

from ee_formation_env.baselines.learned.options import TrainingOptions  # noqa: E402
from ee_formation_env.baselines.learned.training_env import BatchedTrainingEnv  # noqa: E402

# The plain torque-mode training env: no features, no shaping.
TORQUE = TrainingOptions(mode="torque", obs_features="none", hold_penalty=0.0)
from ee_formation_env.integrations.sb3 import STOPPED_WORKER_SECONDS, SharedPolicyVecEnv, WorkerFault  # noqa: E402

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="signals and /proc (Linux)")

REPO = Path(__file__).resolve().parents[2]


def _factory():
    return functools.partial(BatchedTrainingEnv, "planar_square", {"episode_seconds": 0.05}, TORQUE)


def _gone(pid: int) -> bool:
    """No such process any more (or only its zombie, waiting for a reaper that is not this process)."""
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().rsplit(")", 1)[1].split()[0] in ("Z", "X")
    except FileNotFoundError:
        return True


def _wait_gone(pids, seconds: float) -> bool:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if all(_gone(pid) for pid in pids):
            return True
        time.sleep(0.05)
    return all(_gone(pid) for pid in pids)


def _assert_no_worker_left(pids) -> None:
    assert not [p for p in multiprocessing.active_children() if p.pid in pids]
    assert all(not os.path.exists(f"/proc/{pid}") for pid in pids)  # ended and reaped


def _actions(venv):
    return np.zeros((venv.num_envs, 2), dtype=np.float32)


def test_a_killed_worker_is_named_with_its_exit_signal():
    venv = SharedPolicyVecEnv(_factory(), 3, n_workers=1, in_process_envs=1)
    pids = venv.worker_pids()
    try:
        venv.reset()
        os.kill(pids[0], signal.SIGKILL)
        start = time.monotonic()
        with pytest.raises(RuntimeError) as fault:
            venv.step(_actions(venv))
        assert time.monotonic() - start < 3.0
        assert str(fault.value) == (f"env worker 0 (pid {pids[0]}, envs 1-2 of planar_square) died "
                                    f"(exit code -9: SIGKILL) during step")
        with pytest.raises(RuntimeError, match=r"unusable after a worker fault \(env worker 0 .* died"):
            venv.reset()
    finally:
        start = time.monotonic()
        venv.close()
        assert time.monotonic() - start < 3.0
    _assert_no_worker_left(pids)


def test_a_stopped_worker_is_named_within_seconds_whatever_the_timeout_and_close_kills_it():
    venv = SharedPolicyVecEnv(_factory(), 2, n_workers=2, worker_timeout=None)  # waiting forever for an answer
    pids = venv.worker_pids()
    try:
        venv.reset()
        os.kill(pids[1], signal.SIGSTOP)
        start = time.monotonic()
        with pytest.raises(TimeoutError) as fault:
            venv.step(_actions(venv))
        assert STOPPED_WORKER_SECONDS <= time.monotonic() - start < STOPPED_WORKER_SECONDS + 3.0
        assert isinstance(fault.value, WorkerFault) and fault.value.index == 1
        assert str(fault.value) == (f"env worker 1 (pid {pids[1]}, env 1 of planar_square) is stopped (SIGSTOP) "
                                    f"during step: seen stopped for 2 s, it cannot answer until it is continued "
                                    f"(SIGCONT)")
    finally:
        start = time.monotonic()
        venv.close()  # the stopped worker is killed, the healthy one closes
        assert time.monotonic() - start < 5.0
    _assert_no_worker_left(pids)


def test_worker_errors_name_the_worker_and_carry_its_traceback():
    bad = functools.partial(BatchedTrainingEnv, "planar_square", {"episode_seconds": 0.05}, TORQUE)
    venv = SharedPolicyVecEnv(bad, 1, n_workers=1)
    pids = venv.worker_pids()
    try:
        venv.reset()
        with pytest.raises(RuntimeError) as fault:
            venv.step(np.zeros((venv.num_envs, 3), dtype=np.float32))  # wrong action shape
        message = str(fault.value)
        assert message.startswith(f"SharedPolicyVecEnv worker failed: env worker 0 (pid {pids[0]}, env 0 of "
                                  f"planar_square) raised ValueError('actions: expected shape (1, 8) or (4, 2) or "
                                  f"(1, 4, 2), got (4, 3)') during step\nWorker traceback:\nTraceback (most recent "
                                  f"call last):")
    finally:
        venv.close()
    _assert_no_worker_left(pids)


def test_workers_ignore_sigint_but_not_sigterm():
    venv = SharedPolicyVecEnv(_factory(), 2, n_workers=1, in_process_envs=1)
    pids = venv.worker_pids()
    try:
        venv.reset()
        os.kill(pids[0], signal.SIGINT)  # what a Ctrl-C sends to every process of the group
        time.sleep(0.5)
        for _ in range(6):  # across an auto-reset: the worker still steps
            venv.step(_actions(venv))
        assert venv.worker_pids() == pids
        os.kill(pids[0], signal.SIGTERM)
        with pytest.raises(RuntimeError, match=rf"^env worker 0 \(pid {pids[0]}, env 1 of planar_square\) died "
                                               r"\(exit code -15: SIGTERM\) during step$"):
            venv.step(_actions(venv))
    finally:
        venv.close()
    _assert_no_worker_left(pids)


def test_a_worker_exits_when_its_learner_closes_the_pipe():
    venv = SharedPolicyVecEnv(_factory(), 1, n_workers=1)
    process = venv._processes[0]
    try:
        venv._connections[0].close()  # as the learner's death would
        process.join(timeout=5.0)
        assert process.exitcode == 0  # it left its loop and closed its envs
    finally:
        venv._connections, venv._processes = [], []
        venv.close()


def test_workers_exit_when_their_learner_is_killed():
    learner = textwrap.dedent("""
        import functools, sys, time
        from ee_formation_env.baselines.learned.training_env import BatchedTrainingEnv
        from ee_formation_env.integrations.sb3 import SharedPolicyVecEnv
        if __name__ == "__main__":
            factory = functools.partial(BatchedTrainingEnv, "planar_square", {"episode_seconds": 0.05})
            venv = SharedPolicyVecEnv(factory, 2, n_workers=2)
            venv.reset()
            print(*venv.worker_pids(), flush=True)
            time.sleep(120)
    """)
    process = subprocess.Popen([sys.executable, "-c", learner], cwd=REPO, stdout=subprocess.PIPE, text=True)
    try:
        pids = [int(pid) for pid in process.stdout.readline().split()]
        assert len(pids) == 2 and all(not _gone(pid) for pid in pids)
    finally:
        process.kill()
        process.wait(timeout=10)
    left = [] if _wait_gone(pids, 5.0) else [pid for pid in pids if not _gone(pid)]
    for pid in left:  # not to leave them to the next tests
        os.kill(pid, signal.SIGKILL)
    assert not left


def test_ctrl_c_reaches_the_learner_alone():
    """SIGINT to the whole process group: the learner gets its KeyboardInterrupt, its workers keep stepping."""
    learner = textwrap.dedent("""
        import functools, signal, time
        import numpy as np
        from ee_formation_env.baselines.learned.training_env import BatchedTrainingEnv
        from ee_formation_env.integrations.sb3 import SharedPolicyVecEnv
        if __name__ == "__main__":
            # A learner in a terminal: a shell's background job (CI) starts with SIGINT ignored, and the
            # ignoring is inherited, so without this line no KeyboardInterrupt would ever come.
            signal.signal(signal.SIGINT, signal.default_int_handler)
            factory = functools.partial(BatchedTrainingEnv, "planar_square", {"episode_seconds": 0.05})
            venv = SharedPolicyVecEnv(factory, 2, n_workers=1, in_process_envs=1)
            venv.reset()
            try:
                print("ready", flush=True)  # inside the try: the signal may arrive as soon as the line is read
                # Short sleeps: the kernel may hand the SIGINT to another thread (numpy's BLAS threads do not
                # block it), and then Python raises it only when the main thread next runs bytecode.
                for _ in range(600):
                    time.sleep(0.1)
            except KeyboardInterrupt:
                for _ in range(6):  # what a learner saving its model does not need, but may: the workers live
                    venv.step(np.zeros((venv.num_envs, 2), dtype=np.float32))
                print("stepped after Ctrl-C", flush=True)
            venv.close()
    """)
    process = subprocess.Popen([sys.executable, "-c", learner], cwd=REPO, stdout=subprocess.PIPE, text=True,
                               start_new_session=True)
    try:
        assert process.stdout.readline() == "ready\n"
        os.killpg(process.pid, signal.SIGINT)
        out, _ = process.communicate(timeout=30)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait(timeout=10)
    assert out == "stepped after Ctrl-C\n" and process.returncode == 0

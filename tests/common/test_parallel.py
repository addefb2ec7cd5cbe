"""The local process pool's workers end with the process that made them."""
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

PARENT = textwrap.dedent("""
    import os, sys, time
    from so_transients.common.parallel import executor

    def task(folder):
        (folder / f"{os.getpid()}.pid").write_text("")
        time.sleep(120)

    if __name__ == "__main__":
        from pathlib import Path
        pool, _ = executor(2)
        folder = Path(sys.argv[1])
        futures = [pool.submit(task, folder) for _ in range(2)]
        time.sleep(120)
""")


def running(pid: int) -> bool:
    """Whether ``pid`` is a process that has not ended (a zombie has)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, ProcessLookupError):
        return False
    return state not in ("Z", "X")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="prctl is Linux's")
@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM], ids=["SIGKILL", "SIGTERM"])
def test_workers_end_with_the_process_that_made_them(tmp_path, sig):
    """Killed however (SIGKILL: as the out-of-memory killer does), the parent leaves no worker
    running its task (the tasks sleep two minutes)."""
    script = tmp_path / "parent.py"
    script.write_text(PARENT)
    proc = subprocess.Popen([sys.executable, str(script), str(tmp_path)],
                            env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
    try:
        deadline = time.monotonic() + 60
        while len(list(tmp_path.glob("*.pid"))) < 2:
            assert proc.poll() is None, "the parent ended before its workers started"
            assert time.monotonic() < deadline, "the workers never started"
            time.sleep(0.1)
        workers = [int(p.stem) for p in tmp_path.glob("*.pid")]
        assert all(running(pid) for pid in workers)
        proc.send_signal(sig)
        proc.wait(10)
        deadline = time.monotonic() + 10
        while any(running(pid) for pid in workers) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not any(running(pid) for pid in workers), "a worker outlived its parent"
    finally:
        proc.kill()
        proc.wait()
        for pid in [int(p.stem) for p in tmp_path.glob("*.pid")]:
            if running(pid):
                os.kill(pid, signal.SIGKILL)

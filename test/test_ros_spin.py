"""Tests of gcn_match_ros.ros.spin: stop_node_process stops a child like Ctrl-C, killing it after the timeout."""
import signal
import subprocess
import sys

from gcn_match_ros.ros.spin import stop_node_process

# A child that says "ready" once its SIGINT handling is in place, then waits.
EXITS_ON_SIGINT = ("import signal, sys, time\n"
                   "signal.signal(signal.SIGINT, lambda *a: sys.exit(3))\n"
                   "print('ready', flush=True)\n"
                   "time.sleep(60)\n")
IGNORES_SIGINT = ("import signal, time\n"
                  "signal.signal(signal.SIGINT, signal.SIG_IGN)\n"
                  "print('ready', flush=True)\n"
                  "time.sleep(60)\n")


def start(code: str) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "ready"
    return proc


def test_a_child_that_exits_on_sigint_exits_by_itself():
    proc = start(EXITS_ON_SIGINT)
    try:
        stop_node_process(proc, timeout=30)
        assert proc.returncode == 3  # its own exit status: it handled the SIGINT, it was not killed
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.stdout.close()


def test_a_child_that_ignores_sigint_is_killed_after_the_timeout():
    proc = start(IGNORES_SIGINT)
    try:
        stop_node_process(proc, timeout=0.3)
        assert proc.returncode == -signal.SIGKILL
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.stdout.close()


def test_a_child_that_has_exited_is_left_alone():
    proc = subprocess.Popen([sys.executable, "-c", "import sys; sys.exit(5)"])
    proc.wait()
    stop_node_process(proc, timeout=0.1)
    assert proc.returncode == 5

"""What `up` starts dies with it, or the next `up` finds it in the pid file and ends it, never
touching a process that is not the recorded one."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

from mapservice.local import lifetime

SLEEPER = [sys.executable, "-c", "import time; time.sleep(120)"]


def wait_gone(pid: int, timeout_s: float = 10) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if lifetime.start_time(pid) is None:
            return True
        time.sleep(0.05)
    return False


def test_a_child_started_with_die_with_parent_ends_when_its_parent_is_killed(tmp_path):
    """The parent (as `up`) starts a child in a session of its own with the preexec, then is
    killed with SIGKILL: the child gets SIGTERM and ends. Its files are 0600 (umask 077)."""
    child_code = "import sys, time; open(sys.argv[1], 'w').close(); time.sleep(120)"
    code = (
        "import subprocess, sys, time\n"
        "from mapservice.local.lifetime import die_with_parent\n"
        f"child = subprocess.Popen([sys.executable, '-c', {child_code!r}, sys.argv[1]],"
        " start_new_session=True, preexec_fn=die_with_parent)\n"
        "print(child.pid, flush=True)\n"
        "time.sleep(120)\n"
    )
    made = tmp_path / "made-by-child"
    parent = subprocess.Popen(
        [sys.executable, "-c", code, str(made)], stdout=subprocess.PIPE, text=True
    )
    child = int(parent.stdout.readline())
    try:
        deadline = time.monotonic() + 10
        while not made.exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        assert made.stat().st_mode & 0o777 == 0o600
        assert lifetime.start_time(child) is not None
        parent.kill()
        parent.wait()
        assert wait_gone(child), "the child outlived its killed parent"
    finally:
        if lifetime.start_time(child) is not None:
            os.kill(child, signal.SIGKILL)


def test_the_next_up_ends_what_the_last_one_left_and_only_that(tmp_path):
    """A pid file written by an `up` that no longer runs names two components still running:
    both are found and ended (their process groups). A recorded pid whose process is not the
    recorded one (its start time or command differs: the pid was reused) is left alone."""
    pid_file = lifetime.PidFile.in_data_dir(tmp_path)
    left = [subprocess.Popen(SLEEPER, start_new_session=True) for _ in range(2)]
    stranger = subprocess.Popen(SLEEPER, start_new_session=True)
    try:
        pid_file.write({"gateway": left[0].pid, "server": left[1].pid})
        assert oct(pid_file.path.stat().st_mode & 0o777) == oct(0o600)
        record = pid_file.path.read_text()
        # As if `up` had been another, dead process, and `mqtt` a process since replaced by
        # the stranger under the same pid.
        dead = subprocess.Popen([sys.executable, "-c", "pass"])
        dead.wait()
        import json

        data = json.loads(record)
        data["up"]["pid"] = dead.pid
        data["components"].append(
            {"name": "mqtt", "pid": stranger.pid, "start": 1, "command": ["/usr/sbin/mosquitto"]}
        )
        pid_file.path.write_text(json.dumps(data))
        assert pid_file.running_up() is None
        found = pid_file.leftovers()
        assert sorted(p.name for p in found) == ["gateway", "server"]
        lifetime.end(found)
        assert all(p.wait(10) == -signal.SIGTERM for p in left)
        assert stranger.poll() is None, "a process that only has a recorded pid was ended"
    finally:
        for proc in (*left, stranger):
            if proc.poll() is None:
                proc.kill()
                proc.wait()


def test_a_running_up_is_found_and_its_components_are_not_leftovers(tmp_path):
    """While the `up` that wrote the pid file runs, another `up` is told so and ends nothing."""
    up = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time\n"
            "from mapservice.local.lifetime import PidFile\n"
            f"PidFile.in_data_dir({str(tmp_path)!r}).write({{}})\n"
            "print('written', flush=True); time.sleep(120)",
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert up.stdout.readline().strip() == "written"
        pid_file = lifetime.PidFile.in_data_dir(tmp_path)
        running = pid_file.running_up()
        assert running is not None and running.pid == up.pid
        assert pid_file.leftovers() == []
    finally:
        up.kill()
        up.wait()
    assert lifetime.PidFile.in_data_dir(tmp_path).running_up() is None


def test_the_guard_stops_the_components_in_order_when_up_is_killed(tmp_path):
    """`up` (here a stand-in) records a guard and two components, then is killed with
    SIGKILL: the guard stops the gateway first, and only once it has exited the broker
    (all at once, the broker quit first: it has nothing to finish)."""
    log = tmp_path / "stopped"
    component = (
        "import signal, sys, time\n"
        "def stop(*_):\n"
        "    time.sleep(float(sys.argv[2]))\n"
        f"    open({str(log)!r}, 'a').write(sys.argv[1] + chr(10)); sys.exit(0)\n"
        "signal.signal(signal.SIGTERM, stop)\n"
        "print('ready', flush=True)\n"
        "while True: time.sleep(1)\n"
    )
    up_code = (
        "import subprocess, sys, time, os\n"
        "from pathlib import Path\n"
        "from mapservice.local import lifetime\n"
        f"pid_file = lifetime.PidFile.in_data_dir({str(tmp_path)!r})\n"
        f"component = {component!r}\n"
        "procs = {name: subprocess.Popen([sys.executable, '-c', component, name, delay],"
        " start_new_session=True, stdout=subprocess.PIPE, text=True)"
        " for name, delay in (('kafka', '0'), ('gateway', '1'))}\n"
        "for proc in procs.values(): proc.stdout.readline()\n"
        "guard = subprocess.Popen([sys.executable, '-m', 'mapservice.local.lifetime', 'guard',"
        " str(pid_file.path), str(os.getpid()), lifetime.mark_children(), '1'],"
        " start_new_session=True, preexec_fn=lifetime.guard_preexec)\n"
        "pids = {name: p.pid for name, p in procs.items()}\n"
        "pids['guard'] = guard.pid\n"
        "pid_file.write(pids)\n"
        "print(' '.join(str(p) for p in pids.values()), flush=True)\n"
        "time.sleep(120)\n"
    )
    up = subprocess.Popen([sys.executable, "-c", up_code], stdout=subprocess.PIPE, text=True)
    pids = [int(p) for p in up.stdout.readline().split()]
    try:
        time.sleep(1.5)  # the guard has installed its signal handler
        up.kill()
        up.wait()
        assert all(wait_gone(pid, 20) for pid in pids), "the guard did not end them"
        assert log.read_text().split() == ["gateway", "kafka"]
    finally:
        for pid in pids:
            if lifetime.start_time(pid) is not None:
                os.kill(pid, signal.SIGKILL)


# A stand-in for `up` that marks its children, records a guard, starts components and
# records only the first `recorded` of them (the others as if `up` died between starting
# them and recording them), then prints the pids and waits to be killed.
UNRECORDED_UP = (
    "import subprocess, sys, os, time\n"
    "from mapservice.local import lifetime\n"
    "pid_file = lifetime.PidFile.in_data_dir(sys.argv[1])\n"
    "mark = lifetime.mark_children()\n"
    "guard = subprocess.Popen([sys.executable, '-m', 'mapservice.local.lifetime', 'guard',"
    " str(pid_file.path), str(os.getpid()), mark, '1'], start_new_session=True,"
    " preexec_fn=lifetime.guard_preexec)\n"
    "components = [subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(120)'],"
    " start_new_session=True) for _ in range(3)]\n"
    "recorded = int(sys.argv[2])\n"
    "pid_file.write({'guard': guard.pid, **{f'gateway-{i}': p.pid"
    " for i, p in enumerate(components[:recorded])}})\n"
    "print(guard.pid, *(p.pid for p in components), flush=True)\n"
    "time.sleep(120)\n"
)


def start_unrecorded_up(tmp_path, recorded: int) -> tuple[subprocess.Popen, int, list[int]]:
    up = subprocess.Popen(
        [sys.executable, "-c", UNRECORDED_UP, str(tmp_path), str(recorded)],
        stdout=subprocess.PIPE,
        text=True,
    )
    guard, *components = (int(p) for p in up.stdout.readline().split())
    return up, guard, components


def test_the_guard_ends_components_up_started_and_had_not_recorded_when_killed(tmp_path):
    """`up` is killed after starting components it had not recorded yet (0, 1 or 2 of the
    three recorded: as if killed between a start and its record, on any start thread), at
    once (the guard's interpreter still starting) or once the guard waits: the guard ends
    every one of them, found by `up`'s mark."""
    for recorded in range(3):
        for pause_s in (0.0, 1.5):
            data_dir = tmp_path / f"{recorded}-{pause_s}"
            up, guard, components = start_unrecorded_up(data_dir, recorded)
            try:
                time.sleep(pause_s)
                up.kill()
                up.wait()
                survivors = [pid for pid in components if not wait_gone(pid, 20)]
                assert not survivors, (
                    f"{recorded} of 3 recorded, killed after {pause_s} s: {survivors} outlived up"
                )
                assert wait_gone(guard, 10)
            finally:
                for pid in (guard, *components):
                    if lifetime.start_time(pid) is not None:
                        os.kill(pid, signal.SIGKILL)


def test_the_next_up_ends_unrecorded_components_of_a_dead_up_whose_guard_died_too(tmp_path):
    """The guard is killed with `up`: the next `up` finds the components the record names
    and those carrying the dead `up`'s mark that it does not name, and ends them all; a
    process that carries another `up`'s mark is left alone."""
    up, guard, components = start_unrecorded_up(tmp_path, 1)
    env = {**os.environ, lifetime.MARK_ENV: lifetime.mark_of(up.pid, 1)}  # another `up`
    stranger = subprocess.Popen(SLEEPER, start_new_session=True, env=env)
    try:
        os.kill(guard, signal.SIGKILL)
        assert wait_gone(guard)
        up.kill()
        up.wait()
        found = lifetime.PidFile.in_data_dir(tmp_path).leftovers()
        assert sorted(p.pid for p in found) == sorted(components)
        assert sorted(p.name for p in found) == ["gateway-0", "unrecorded", "unrecorded"]
        lifetime.end(found)
        assert all(wait_gone(pid) for pid in components)
        assert stranger.poll() is None
    finally:
        for pid in (guard, *components):
            if lifetime.start_time(pid) is not None:
                os.kill(pid, signal.SIGKILL)
        stranger.kill()
        stranger.wait()


# A stand-in for `up` that records a guard and forks a component whose program runs only
# `late_s` after the fork (its preexec_fn waits, as a child forked on a loaded machine just
# before `up` died may): `up` is killed meanwhile, before the component shows the mark.
LATE_EXEC_UP = (
    "import subprocess, sys, os, time\n"
    "from mapservice.local import lifetime\n"
    "pid_file = lifetime.PidFile.in_data_dir(sys.argv[1])\n"
    "mark = lifetime.mark_children()\n"
    "guard = subprocess.Popen([sys.executable, '-m', 'mapservice.local.lifetime', 'guard',"
    " str(pid_file.path), str(os.getpid()), mark, sys.argv[3]], start_new_session=True,"
    " preexec_fn=lifetime.guard_preexec)\n"
    "pid_file.write({'guard': guard.pid})\n"
    "pid = os.fork()\n"
    "if pid == 0:\n"
    "    time.sleep(float(sys.argv[2]))\n"
    "    os.execv(sys.executable, [sys.executable, '-c', 'import time; time.sleep(120)'])\n"
    "print(guard.pid, pid, flush=True)\n"
    "time.sleep(120)\n"
)


def test_the_guard_ends_a_component_that_runs_its_program_seconds_after_up_died(tmp_path):
    """A component forked just before `up` died and running its program only seconds later
    (a loaded machine) shows `up`'s mark only then: the guard keeps looking until none has
    turned up for its settle time, and ends it."""
    for late_s in (0.5, 3.0):
        up = subprocess.Popen(
            [sys.executable, "-c", LATE_EXEC_UP, str(tmp_path / str(late_s)), str(late_s), "5"],
            stdout=subprocess.PIPE,
            text=True,
        )
        guard, late = (int(p) for p in up.stdout.readline().split())
        try:
            time.sleep(1.0)  # the guard waits; the component has not run its program yet
            up.kill()
            up.wait()
            assert wait_gone(late, 30), (
                f"a component running its program {late_s} s late outlived up"
            )
            assert wait_gone(guard, 30)
        finally:
            for pid in (guard, late):
                if lifetime.start_time(pid) is not None:
                    os.kill(pid, signal.SIGKILL)


# A guard whose threading.Event holds its lock nearly all the time, as Event.wait does for a
# moment at its start and its end: a SIGTERM handler that needs that lock, run by Python in
# such a moment, waits for itself for ever. The guard must act whatever its main thread holds.
HELD_LOCK_GUARD = (
    "import runpy, sys, threading, time\n"
    "class HeldEvent(threading.Event):\n"
    "    def wait(self, timeout=None):\n"
    "        with self._cond:\n"
    "            time.sleep(0.5)\n"
    "        return super().wait(0.01)\n"
    "threading.Event = HeldEvent\n"
    "sys.argv = ['lifetime', 'guard', *sys.argv[1:]]\n"
    "runpy.run_module('mapservice.local.lifetime', run_name='__main__')\n"
)


def test_the_guard_acts_on_up_s_death_whatever_its_main_thread_holds(tmp_path):
    """The parent-death signal reaches the guard while its main thread holds a lock a signal
    handler would need: the guard still ends the recorded component, and itself."""
    pid_file = lifetime.PidFile.in_data_dir(tmp_path)
    component = subprocess.Popen(SLEEPER, start_new_session=True)
    pid_file.write({"gateway-0": component.pid})
    guard = subprocess.Popen(
        [
            sys.executable,
            "-c",
            HELD_LOCK_GUARD,
            str(pid_file.path),
            str(os.getpid()),
            "no-mark",
            "1",
        ],
        start_new_session=True,
        preexec_fn=lifetime.guard_preexec,
    )
    try:
        time.sleep(1.5)  # the guard waits for the signal (its interpreter started)
        guard.send_signal(signal.SIGTERM)
        try:
            component.wait(15)
        except subprocess.TimeoutExpired:
            raise AssertionError("the guard did not end the component") from None
        assert guard.wait(15) == 0
    finally:
        for process in (guard, component):
            if process.poll() is None:
                process.kill()
                process.wait()

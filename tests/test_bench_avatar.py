"""bench.avatar's own arithmetic: the CPU of a process tree read from /proc, and the page's frame rates."""

from __future__ import annotations

import subprocess
import sys
import time

import pytest

from bench.avatar import ProcessTreeCpu, frame_rates, spread

BURN = "import time\nend = time.process_time() + {s}\nwhile time.process_time() < end: pass\n"


def test_a_process_trees_cpu_counts_its_descendants_even_after_they_exit():
    child = BURN.format(s=0.3)
    parent = f"import subprocess, sys\nsubprocess.run([sys.executable, '-c', {child!r}])\n" + BURN.format(s=0.3)
    proc = subprocess.Popen([sys.executable, "-c", parent])
    tree = ProcessTreeCpu(proc.pid)
    pids = set()
    while proc.poll() is None:  # the grandchild burns first, exits, then its parent burns
        tree.sample()
        pids |= set(tree.ticks)
        time.sleep(0.02)
    assert len(pids) >= 2 and proc.returncode == 0
    assert tree.seconds() >= 0.5  # both burns (the last ticks of the parent may be missed after it exits)


def _sample(t_ms, draws, frames=0):
    return {"t_ms": t_ms, "avatar": {"draws": draws}, "dash": {"frames": frames}}


def test_frame_rates_are_per_second_of_page_time_between_the_first_and_last_frame():
    samples = [_sample(0, 5), _sample(1000, 5), _sample(2000, 35), _sample(2500, 45), _sample(3500, 45)]
    assert frame_rates(samples, "browser") == [30.0, 20.0]  # idle before and after: left out
    assert frame_rates(samples, "server") == []
    server = [_sample(0, 0, 0), _sample(1000, 0, 25), _sample(2000, 0, 49)]
    assert frame_rates(server, "server") == [25.0, 24.0]
    assert spread([30.0, 20.0, None]) == {"median": 25.0, "p5": 20.5, "min": 20.0, "n": 2}
    assert spread([]) == {"n": 0}


def test_the_bench_refuses_an_unknown_mode():
    from bench.avatar import main

    with pytest.raises(SystemExit):
        main(["--modes", "client"])

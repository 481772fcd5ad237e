"""Issue 46, case 10: every bus listener beyond loopback is named in a warning with its option, and the log says
where each endpoint really listens."""

from __future__ import annotations

import re
import socket

import pytest

from ecas.core.bus import beyond_loopback
from tests.test_reliability_runtime import ipc_dirs, launch, recording
from tests.test_runtime import finish, leftovers


@pytest.mark.parametrize(
    ("address", "beyond"),
    [
        ("ipc:///tmp/ecas-1-x/io.sock", False),
        ("tcp://127.0.0.1:5600", False),
        ("tcp://127.0.0.2:5600", False),
        ("tcp://localhost:5600", False),
        ("tcp://[::1]:5600", False),
        ("tcp://0.0.0.0:5600", True),
        ("tcp://*:5600", True),
        ("tcp://[::]:5600", True),
        ("tcp://192.168.1.20:5600", True),
        ("tcp://gpu-box:5600", True),
        ("tcp://eth0:5600", True),
    ],
)
def test_which_addresses_other_machines_reach(address, beyond):
    assert beyond_loopback(address) is beyond


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def test_a_public_bus_endpoint_is_warned_about_and_logged_where_it_listens(tmp_path):
    port = free_port()
    tcp = [
        "--set",
        "bus.transport=tcp",
        "--set",
        "bus.base_port=0",
        "--set",
        f"bus.endpoints.render=tcp://0.0.0.0:{port}",
    ]
    proc = launch(["--replay", str(recording(tmp_path / "talk.wav", 1.0)), "--fast", *tcp], tmp_path / "run")
    code, output = finish(proc)
    assert code == 0, output
    warnings = [line for line in output.splitlines() if " WARNING: bus: " in line]
    assert len(warnings) == 1, output
    assert f"render listens on tcp://0.0.0.0:{port} (bus.endpoints.render)" in warnings[0]
    started = re.search(r"started: .* \(bus: (.*)\)", output).group(1)
    assert f"render tcp://0.0.0.0:{port}" in started and "io tcp://127.0.0.1:" in started, started
    assert "supervisor tcp://127.0.0.1:" in started
    assert leftovers(proc.pid) == [] and ipc_dirs(proc.pid) == []


def test_bus_host_beyond_loopback_warns_for_every_endpoint(tmp_path):
    tcp = ["--set", "bus.transport=tcp", "--set", "bus.base_port=0", "--set", "bus.host=0.0.0.0"]
    proc = launch(["--replay", str(recording(tmp_path / "talk.wav", 1.0)), "--fast", *tcp], tmp_path / "run")
    code, output = finish(proc)
    assert code == 0, output
    warned = re.findall(r" WARNING: bus: (\w+) listens on tcp://0\.0\.0\.0:\d+ \(bus\.host\)", output)
    assert sorted(warned) == ["dialogue", "gesture", "io", "render", "supervisor"], output
    assert leftovers(proc.pid) == [] and ipc_dirs(proc.pid) == []

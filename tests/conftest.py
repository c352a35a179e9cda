"""Shared test fixtures: the reference vehicle and small helpers to vary it."""

from __future__ import annotations

import os

# BLAS started single-threaded, as Dask's nanny starts its workers and `jetloop campaign` its
# serial runs (ground.cli.SINGLE_THREAD_BLAS): the campaign tests compare a serial run in this
# process with a cluster's bit for bit, and OpenBLAS 0.3.31 started with threads rounds a
# mission's figures differently in the 10th digit. Set before numpy is first imported
from ground.cli import SINGLE_THREAD_BLAS  # noqa: E402 (it imports no numpy)

for _var in SINGLE_THREAD_BLAS:
    os.environ.setdefault(_var, "1")

import socket  # noqa: E402
from pathlib import Path

import pytest  # noqa: E402

from onboard.vehicle import EFFECT_IDS, Vehicle, load_vehicle  # noqa: E402

# The shared project tree (specs, reference vehicle, real ArduSub logs) stands beside the
# repository, in every developer's checkout and in CI's fresh clone. Tests that read it fail,
# not skip, when it is missing: a test that silently does nothing cannot fail.
SHARED = Path(__file__).resolve().parents[2] / "shared"
SHARED_VEHICLE = SHARED / "vehicles" / "asr4.toml"
ARDUSUB = SHARED / "data" / "ardusub"


def shared_file(path: Path) -> Path:
    """`path` under shared/, or a clear failure saying where it was expected."""
    if not path.exists():
        pytest.fail(f"{path} is missing: the shared project tree must stand beside the repository")
    return path


@pytest.fixture(scope="session")
def vehicle() -> Vehicle:
    """The packaged reference vehicle asr4, every effect as in its file (all on)."""
    return load_vehicle()


def only_effects(vehicle: Vehicle, *effect_ids: str) -> Vehicle:
    """`vehicle` with exactly the named effects on and every other effect off."""
    unknown = set(effect_ids) - set(EFFECT_IDS)
    if unknown:
        raise ValueError(f"unknown effect ids {sorted(unknown)}; known: {EFFECT_IDS}")
    return vehicle.with_effects(**{e: e in effect_ids for e in EFFECT_IDS})


def neutrally_buoyant(vehicle: Vehicle) -> Vehicle:
    """`vehicle` with its volume set so that rho g V = m g (buoyancy equals weight)."""
    return vehicle.with_values({"body.volume": vehicle.body.mass / vehicle.environment.rho})


@pytest.fixture(scope="session")
def reference_text() -> str:
    """The text of the packaged reference vehicle file, for tests that edit it."""
    from onboard.vehicle import DEFAULT_VEHICLE

    return DEFAULT_VEHICLE.read_text(encoding="utf-8")


@pytest.fixture
def ardusub_data() -> Path:
    """The real BlueROV2/ArduSub recordings of shared/data/ardusub (fails if they are missing)."""
    return shared_file(ARDUSUB)


def free_udp_port() -> int:
    """A UDP port on 127.0.0.1 that was free a moment ago (for a process that binds it itself)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def loop_pair(vehicle):
    """An onboard loop on the reference vehicle (lock-step clock) whose link talks to a ground
    link over real loopback UDP: (loop, ground), the loop's hello already received."""
    from onboard.link import Link
    from onboard.loop import OnboardLoop, VehicleClock

    ground = Link("udpin:127.0.0.1:0")
    link = Link(f"udpout:127.0.0.1:{ground.local_address[1]}")
    loop = OnboardLoop(vehicle, link, VehicleClock())
    loop.start()
    assert ground.recv(2.0).get_type() == "HEARTBEAT"
    yield loop, ground
    link.close()
    ground.close()

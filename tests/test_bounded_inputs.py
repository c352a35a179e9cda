"""No input file is read whole unless it is a regular file of a sane size (adversarial run after
issue 15: /dev/zero as a vehicle, key, commands or recording file grew every command to GBs),
and a vehicle file nested thousands deep or with thousands of problems gives one short error."""

from __future__ import annotations

import errno
import os
import threading

import pytest

from ground.cli import main
from onboard.files import read_bounded
from onboard.vehicle import VehicleFileError, parse_vehicle, vehicle_from_dict


def test_read_bounded_refuses_devices_pipes_and_oversized_files(tmp_path):
    f = tmp_path / "f"
    f.write_bytes(b"x" * 100)
    assert read_bounded(f, 100) == b"x" * 100
    with pytest.raises(OSError) as big:
        read_bounded(f, 99)
    assert big.value.errno == errno.EFBIG and "larger than 99 bytes" in big.value.strerror
    with pytest.raises(OSError) as dev:
        read_bounded("/dev/zero", 10)
    assert dev.value.errno == errno.EINVAL and "not a regular file" in dev.value.strerror
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    os.set_blocking(os.open(fifo, os.O_RDONLY | os.O_NONBLOCK), False)  # a reader, so open() does not block
    w = os.open(fifo, os.O_WRONLY | os.O_NONBLOCK)
    try:
        with pytest.raises(OSError, match="not a regular file"):
            read_bounded(fifo, 10)
    finally:
        os.close(w)


def test_read_bounded_does_not_wait_for_a_fifo_writer(tmp_path):
    """A FIFO nobody writes to: open() alone would block for ever (found by the review)."""
    fifo = tmp_path / "lonely"
    os.mkfifo(fifo)
    out = []

    def read():
        try:
            read_bounded(fifo, 10)
        except OSError as exc:
            out.append(exc)

    t = threading.Thread(target=read, daemon=True)
    t.start()
    t.join(5.0)
    if t.is_alive():  # unblock the thread before failing
        os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        pytest.fail("read_bounded waited for a writer on a FIFO")
    assert out and "not a regular file" in out[0].strerror


@pytest.mark.parametrize("argv", [
    ["sim", "--vehicle", "/dev/zero", "--commands", "CMDS", "--out", "OUT"],
    ["sim", "--commands", "/dev/zero", "--out", "OUT"],
    ["diagnose", "/dev/zero"],
    ["plot", "/dev/zero", "--out", "OUT"],
    ["onboard", "--link", "udpin:127.0.0.1:0", "--key", "/dev/zero"],
    ["identify", "thrust", "/dev/zero"],  # read until memory ran out (issue 15 re-run)
    ["identify", "free-decay", "/dev/zero", "--spring", "50"],
])
def test_every_command_refuses_a_device_as_a_file_in_one_line(argv, tmp_path, capsys):
    from onboard.cli import __file__ as onboard_cli

    cmds = os.path.join(os.path.dirname(onboard_cli), "data", "demo_commands.csv")
    argv = [a.replace("CMDS", cmds).replace("OUT", str(tmp_path / "out")) for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err
    problems = [line for line in err.splitlines() if not line.startswith("[")]  # (progress lines start "[")
    assert "not a regular file" in err and "Traceback" not in err and len(problems) == 1


def test_deeply_nested_toml_is_one_clear_error():
    with pytest.raises(VehicleFileError, match="nested too deeply"):
        parse_vehicle("a = " + "[" * 5000 + "]" * 5000 + "\n")
    with pytest.raises(VehicleFileError, match="nested too deeply"):
        parse_vehicle("a = " + "{b = " * 3000 + "1" + "}" * 3000 + "\n")


def test_thousands_of_problems_are_counted_not_all_echoed():
    doc = {f"k{i}": 1 for i in range(5000)}
    with pytest.raises(VehicleFileError) as exc:
        vehicle_from_dict(doc, "many.toml")
    msg = str(exc.value)
    assert "problems)" in msg and "... and " in msg and " more" in msg
    assert len(msg.splitlines()) <= 22 and len(msg) < 20_000

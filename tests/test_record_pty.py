"""`jaxcal record --port` end to end on pseudo-terminals, as a user's device would be used (pyserial opens
the pty; tests/ptydev.py plays the module): SIGKILL at random moments loses at most the read in flight
(the frame being decoded while the recorder keeps up), for NLink, DWM1001 TLV (the test answers the
requests) and the DWM1001 shell (`--init`: the test answers `lec`); a killed recording is refused, not
overwritten, and recovered by one command; the faults of a real link (wrong baud, silence, a 10x burst,
unplug and replug at the same path, a device that never comes back) are reported in one line each and
lose no frame; Ctrl-C ends with 130 and a complete file.

The longer soak (hundreds of kills) is benchmarks/record_kill_soak.py."""

from __future__ import annotations

import json
import os
import re
import signal
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import h5py

from conftest import assert_one_line_error, run_cli
from jaxcal.io import hdf5
from ptydev import (
    Device,
    kill_ok,
    kill_run,
    lec_lines,
    nlink_frames,
    open_pty,
    raws,
    rebaud,
    start_recorder,
    tlv_responses,
    wait_drained,
    wait_for,
)

# 20 kills: (protocol, items in the stream); the kill item and the part of it written are drawn per seed
KILLS = [("nlink", 250)] * 8 + [("dwm1001-tlv", 50)] * 6 + [("dwm1001-shell", 50)] * 6


def _h5_frames(path) -> list[bytes]:
    with h5py.File(path, "r") as f:
        data, off = f["raw/frames"][()].tobytes(), f["raw/offsets"][()]
    return [data[off[i] : off[i + 1]] for i in range(off.size - 1)]


def test_sigkill_at_20_random_moments_loses_at_most_the_read_in_flight(tmp_path):
    with ThreadPoolExecutor(4) as pool:  # the recorders mostly wait on the pty: run four at a time
        runs = list(pool.map(lambda a: kill_run(tmp_path, a[1][0], a[0], a[1][1]), enumerate(KILLS)))
    lines = []
    for r in runs:
        assert kill_ok(r), r  # at most the read in flight lost, from the journal and from --raw-out
        assert r["stderr"] == "", r  # --quiet: nothing before the kill
        lines.append(
            f"{r['protocol']:>14} seed {r['seed']:2d}: sent {r['sent']:3d}, read {r['read_complete']:3d}, "
            f"recovered {r['recovered']:3d}, largest read {r['max_read_items']} items"
            f"{' (snapshot existed)' if r['snapshot_at_kill'] else ''}"
        )
    print("\n" + "\n".join(lines))
    by = {}
    for r in runs:
        s = by.setdefault(r["protocol"], [0, 0, 0])
        s[0] += 1
        s[1] += r["sent"]
        s[2] += r["recovered"]
    print({p: {"kills": k, "sent": s, "recovered": v} for p, (k, s, v) in by.items()})

    # a plain record onto the killed recording says what it found and refuses; one command recovers it
    r = next(r for r in runs if r["protocol"] == "nlink" and r["recovered"] >= 20)
    out, journal = r["out"], Path(str(r["out"]) + ".journal")
    before = journal.read_bytes()
    p = run_cli("record", "--port", "/dev/null-not-opened", "--protocol", "nlink", "-o", out)
    assert_one_line_error(p, f"{r['recovered']} frames")
    assert f"jaxcal record --replay {journal} -o {out}" in p.stderr and "nothing was overwritten" in p.stderr
    assert journal.read_bytes() == before
    p = run_cli("record", "--replay", journal, "-o", out)
    assert p.returncode == 0, p.stderr
    assert "recovered" in p.stderr and "journal removed" in p.stderr
    assert _h5_frames(out) == raws("nlink", nlink_frames(250, r["seed"])[: r["recovered"]])
    assert not journal.exists()


def test_decoders_discard_a_cut_frame():
    """A link that breaks mid-frame: the pending bytes are dropped and counted, never parsed (a cut shell
    line `...,6.5` of `...,6.51` would otherwise read as a whole, wrong distance)."""
    from jaxcal.io.serial import make_decoder

    line = lec_lines(1)[0]
    for protocol, item in (
        ("nlink", nlink_frames(1)[0]),
        ("dwm1001-tlv", tlv_responses(1)[0]),
        ("dwm1001-shell", line),
    ):
        dec = make_decoder(protocol)
        cut = len(item) - 3 if protocol == "dwm1001-shell" else len(item) // 2
        assert dec.feed(item[:cut]) == [] and dec.discard() == cut
        assert dec.stats.bytes_skipped == cut and dec.pending == 0
        assert [f.raw for f in dec.feed(item)] == raws(protocol, [item])  # the next one decodes


def _lines_with(text: str, fragment: str) -> int:
    return sum(fragment in line for line in text.splitlines())


def test_link_faults_nlink_unplug_baud_silence_burst_then_ctrl_c(tmp_path):
    """One recording through every fault of a real link; the file holds every valid frame sent."""
    link = tmp_path / "ttyUWB0"  # a stable name, as /dev/serial/by-id/... links are
    master, slave, port = open_pty(link)
    out, raw_out = tmp_path / "faults.h5", tmp_path / "faults.bin"
    proc = start_recorder(port, out, "nlink", "--raw-out", raw_out, "--json")
    err: list[str] = []

    def collect():
        for line in iter(proc.stderr.readline, ""):
            err.append(line)

    reader = threading.Thread(target=collect, daemon=True)
    reader.start()
    frames = nlink_frames(1600, seed=11)
    sent: list[bytes] = []
    stream = bytearray()
    dev = Device("nlink", master)

    def send(fs, period=None):
        if period is not None:
            dev.period = period
        for f in fs:
            dev.send(f)
            sent.append(f)
            stream.extend(f)

    try:
        assert wait_for(lambda: Path(str(out) + ".journal").exists())
        send(frames[:100])  # 1 s at the nominal 100 Hz
        # a module at half the baud rate: the UART reads garbage (2 s of it; reported after 1 s)
        garbage = rebaud(b"".join(frames[100:400]), 0.5)
        assert rebaud(b"".join(frames[100:400]), 1.0) == b"".join(frames[100:400])  # the UART model, right baud
        t_end = time.monotonic() + 2.0
        k = 0
        while time.monotonic() < t_end or k < 300:
            os.write(master, garbage[k : k + 64])
            stream.extend(garbage[k : k + 64])
            k += 64
            time.sleep(0.02)
        send(frames[400:500])  # right again
        time.sleep(3.0)  # the module stops sending (reported after 2 s)
        send(frames[500:550])
        send(frames[550:1250], period=0.001)  # a burst at 10x the nominal rate
        assert wait_drained(slave)
        time.sleep(0.1)
        os.close(master)  # unplugged: the pty goes away, and its name with it
        os.close(slave)
        link.unlink()
        time.sleep(1.0)
        master, slave, _ = open_pty(link)  # plugged back in: a new pty behind the same name
        dev = Device("nlink", master)
        assert wait_for(lambda: any("device back" in line for line in err), 30)  # pyserial flushed on open
        send(frames[1250:1350], period=0.01)
        assert wait_drained(slave)
        time.sleep(0.3)
        proc.send_signal(signal.SIGINT)  # Ctrl-C
        proc.wait(timeout=60)
        reader.join(timeout=10)
        stdout, stderr = proc.stdout.read(), "".join(err)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        os.close(master)
        os.close(slave)
    print("\n" + stderr)
    assert proc.returncode == 130, stderr
    assert "Traceback" not in stderr
    assert stderr.splitlines()[-1].startswith("jaxcal: interrupted (Ctrl-C): recording complete"), stderr
    # one line per fault and one when it ends
    for fragment in (
        "no valid frame: wrong --baud",
        "valid frames again",
        "no data for",
        "data again after",
        "device lost",
        "device back",
    ):
        assert _lines_with(stderr, fragment) == 1, (fragment, stderr)
    assert float(re.search(r"data again after (\d+\.\d) s of silence", stderr).group(1)) >= 2.0
    summary = json.loads(stdout)
    assert summary["stopped"] == "sigint" and summary["link"]["reconnects"] == 1
    assert len(summary["link"]["faults"]) == 6
    # every valid frame, in order, none from the garbage; every byte read in the raw capture
    assert _h5_frames(out) == raws("nlink", sent)
    assert raw_out.read_bytes() == bytes(stream)
    assert not Path(str(out) + ".journal").exists()
    assert hdf5.read(out).node_ids == ("N0", "N1", "N2", "N3")


def test_tlv_module_stops_answering_then_never_comes_back(tmp_path):
    """DWM1001 TLV: the module stops answering (one line, and one when it answers again); then it is
    unplugged for good: exit 3 after --reconnect seconds, one line, the file complete."""
    link = tmp_path / "ttyACM0"
    master, slave, port = open_pty(link)
    out = tmp_path / "tlv.h5"
    proc = start_recorder(port, out, "dwm1001-tlv", "--reconnect", "1", "--quiet")
    answers = tlv_responses(50, seed=4)
    dev = Device("dwm1001-tlv", master)
    try:
        assert wait_for(lambda: Path(str(out) + ".journal").exists())
        for a in answers[:30]:
            assert dev.send(a)
        t_end = time.monotonic() + 3.0  # silence: read and ignore the requests
        while time.monotonic() < t_end:
            dev._wait_request(0.1)
        for a in answers[30:]:
            assert dev.send(a)
        time.sleep(0.3)
        os.close(master)
        os.close(slave)
        link.unlink()
        _, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 3, stderr
    lines = stderr.splitlines()
    assert lines[-1].startswith("jaxcal: the device was lost and did not come back: recording complete"), stderr
    for fragment in (
        "no data for",
        "does not answer",
        "data again after",
        "device lost",
        "did not come back within 1 s",
    ):
        assert _lines_with(stderr, fragment) == 1, (fragment, stderr)
    assert len(lines) == 5 and "Traceback" not in stderr  # four fault lines and the last one
    assert _h5_frames(out) == raws("dwm1001-tlv", answers)
    assert hdf5.read(out).n_ranges == 150


def test_shell_replug_reinit_then_sigterm_and_refusals(tmp_path):
    """DWM1001 shell with --init: unplugged and plugged back, the recorder reopens the port and sends the
    shell entry and `lec` again (a module that was reset starts in TLV mode); SIGTERM: exit 143, one line,
    the file complete. Then an existing OUT.h5 or --raw-out is never written over."""
    link = tmp_path / "ttyACM0"
    master, slave, port = open_pty(link)
    out = tmp_path / "t.h5"
    proc = start_recorder(port, out, "dwm1001-shell", "--quiet")
    err: list[str] = []

    def collect():
        for line in iter(proc.stderr.readline, ""):
            err.append(line)

    reader = threading.Thread(target=collect, daemon=True)
    reader.start()
    lines = lec_lines(40, seed=2)
    try:
        assert wait_for(lambda: Path(str(out) + ".journal").exists())
        dev = Device("dwm1001-shell", master)
        assert dev.begin()  # the first `lec`
        # meanwhile a second recorder on the same port (it would take half of the bytes): the port is locked
        second: list = []
        t = threading.Thread(
            target=lambda: second.append(
                run_cli(
                    "record",
                    "--port",
                    port,
                    "--protocol",
                    "dwm1001-shell",
                    "-o",
                    tmp_path / "second.h5",
                    "--duration",
                    "1",
                )
            )
        )
        t.start()
        for line in lines[:20]:
            dev.send(line)
        t.join(timeout=60)
        assert wait_drained(slave)
        os.close(master)
        os.close(slave)
        link.unlink()
        time.sleep(0.5)
        master, slave, _ = open_pty(link)
        dev = Device("dwm1001-shell", master)
        assert dev.begin()  # `lec` again, after the reconnect
        for line in lines[20:]:
            dev.send(line)
        assert wait_drained(slave)
        time.sleep(0.2)
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=60)
        reader.join(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        os.close(master)
        os.close(slave)
    stderr = "".join(err)
    assert proc.returncode == 143, stderr
    assert len(err) == 3 and ": device lost (" in err[0] and ": device back after" in err[1], stderr
    assert err[-1] == (
        f"jaxcal: terminated (SIGTERM): recording complete, 40 frames, 80 ranges, 0 checksum "
        f"failures, 0 bytes skipped -> {out}\n"
    )
    assert _h5_frames(out) == raws("dwm1001-shell", lines)
    before = out.read_bytes()
    assert_one_line_error(run_cli("record", "--port", port, "--protocol", "nlink", "-o", out), "not overwritten")
    assert_one_line_error(
        run_cli("record", "--port", port, "--protocol", "nlink", "-o", tmp_path / "new.h5", "--raw-out", out),
        "not overwritten",
    )
    assert_one_line_error(run_cli("record", "--replay", out, "-o", out), "is an input of this run")
    assert out.read_bytes() == before and not (tmp_path / "new.h5.journal").exists()
    assert_one_line_error(second[0], "cannot open serial port")
    assert "lock" in second[0].stderr and not (tmp_path / "second.h5.journal").exists()

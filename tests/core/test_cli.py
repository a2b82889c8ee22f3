"""``psm learn`` / ``psm rollout`` / ``psm demo`` through the real entry point (subprocess)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np


def run_psm(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "services.cli", *args], capture_output=True, text=True,
        timeout=120, cwd=cwd,
    )


def test_learn_from_csv_then_rollout_to_a_new_goal(tmp_path: Path, reach_demo) -> None:
    t, X = reach_demo
    csv_path = tmp_path / "demo.csv"
    np.savetxt(csv_path, np.column_stack([t, X]), delimiter=",", header="t,x,y,z", comments="")
    model_path = tmp_path / "model.json"
    learned = run_psm("learn", str(csv_path), "-o", str(model_path), "--plot", str(tmp_path / "r.png"))
    assert learned.returncode == 0, learned.stderr
    assert model_path.exists() and (tmp_path / "r.png").stat().st_size > 10_000
    out = run_psm(
        "rollout", str(model_path), "--goal", "0.5,0.1,0.05", "--csv", str(tmp_path / "r.csv"),
        "--plot", str(tmp_path / "p.png"),
    )
    assert out.returncode == 0, out.stderr
    summary = json.loads(out.stdout)
    assert summary["done"] is True
    np.testing.assert_allclose(summary["final_position"], [0.5, 0.1, 0.05], atol=1e-4)
    rows = np.loadtxt(tmp_path / "r.csv", delimiter=",", skiprows=1)
    assert rows.shape[1] == 1 + 9


def test_learn_from_npz_with_uniform_segments(tmp_path: Path, reach_demo) -> None:
    t, X = reach_demo
    np.savez(tmp_path / "demo.npz", t=t, X=X)
    r = run_psm("learn", str(tmp_path / "demo.npz"), "-o", str(tmp_path / "m.json"), "--segments", "5",
                "--sync", "brake", "--start-shift", "--velocity-extrema")
    assert r.returncode == 0, r.stderr
    data = json.loads((tmp_path / "m.json").read_text())
    assert data["format"] == "psm-model" and len(data["dimensions"][0]["k"]) == 6  # 5 + the speed peak
    assert data["parameters"]["sync_mode"] == "brake" and data["parameters"]["start_shift"] is True
    assert data["parameters"]["velocity_extrema"] is True
    r = run_psm("learn", str(tmp_path / "demo.npz"), "-o", str(tmp_path / "m2.json"),
                "--auto-tolerance", "0.001")
    assert r.returncode == 0, r.stderr
    fine = json.loads((tmp_path / "m2.json").read_text())
    assert fine["parameters"]["auto_tolerance"] == 0.001 and fine["parameters"]["sync_mode"] == "scale"
    assert fine["parameters"]["velocity_extrema"] is True  # the default
    r = run_psm("learn", str(tmp_path / "demo.npz"), "-o", str(tmp_path / "m3.json"), "--segments", "5",
                "--no-velocity-extrema")
    assert r.returncode == 0, r.stderr
    plain = json.loads((tmp_path / "m3.json").read_text())
    assert plain["parameters"]["velocity_extrema"] is False and len(plain["dimensions"][0]["k"]) == 5
    r = run_psm("learn", str(tmp_path / "demo.npz"), "--auto-tolerance", "-1")
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "auto_tolerance" in r.stderr


def test_bad_input_is_one_clear_line(tmp_path: Path) -> None:
    bad = tmp_path / "bad.csv"
    bad.write_text("t,x\n0,0\n1,nan\n")
    r = run_psm("learn", str(bad), "-o", str(tmp_path / "m.json"))
    assert r.returncode == 2
    assert r.stderr.count("\n") == 1 and "error" in r.stderr
    assert "Traceback" not in r.stderr
    r = run_psm("learn", str(tmp_path / "missing.csv"))
    assert r.returncode == 2 and "no such file" in r.stderr
    r = run_psm("learn", str(tmp_path / "demo.txt"))
    assert r.returncode == 2
    # a missing model file: the file name and the reason, not Python's "[Errno 2] ..."
    r = run_psm("rollout", str(tmp_path / "missing.json"))
    assert r.returncode == 2
    assert r.stderr == f"psm rollout: error: {tmp_path / 'missing.json'}: no such file or directory\n"
    # an NPZ without the expected arrays says which ones it found
    np.savez(tmp_path / "lower.npz", t=np.arange(10.0), x=np.arange(10.0))
    r = run_psm("learn", str(tmp_path / "lower.npz"))
    assert r.returncode == 2 and "needs arrays 't' and 'X' (found 't', 'x')" in r.stderr


def test_demo_writes_plots(tmp_path: Path) -> None:
    r = run_psm("demo", "--out", str(tmp_path / "demo"))
    assert r.returncode == 0, r.stderr
    assert "reach_person.mcap" in r.stdout and "reached the goal: True" in r.stdout
    for name in ("model.json", "reproduction.png", "goal_adapted.png", "goal_moved.png", "pushed.png"):
        assert (tmp_path / "demo" / name).exists()


def _one_error_line(r: subprocess.CompletedProcess, command: str = "psm learn") -> str:
    assert r.returncode == 2, r.stderr
    assert r.stderr.count("\n") == 1 and "Traceback" not in r.stderr, r.stderr
    assert r.stderr.startswith(f"{command}: error: "), r.stderr
    return r.stderr[len(f"{command}: error: "):].rstrip("\n")


def test_learn_from_a_damaged_mcap_is_one_line(tmp_path: Path) -> None:
    from services.learn_cli import DEMO_RECORDING

    data = DEMO_RECORDING.read_bytes()
    (tmp_path / "garbage.mcap").write_bytes(b"not an mcap recording\n" * 4)
    msg = _one_error_line(run_psm("learn", str(tmp_path / "garbage.mcap")))
    assert msg == f"{tmp_path / 'garbage.mcap'}: not an MCAP file (no MCAP magic at the start)"
    # truncated after some complete chunks: says so and how much was readable, learns nothing
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) * 2 // 3])
    msg = _one_error_line(run_psm("learn", str(cut), "-o", str(tmp_path / "m.json")))
    assert msg.startswith(f"{cut}: truncated recording (no footer): "), msg
    assert "messages readable in the first " in msg and f"of {len(data) * 2 // 3} bytes" in msg
    assert not (tmp_path / "m.json").exists()
    # bytes damaged inside a chunk
    bad = bytearray(data)
    bad[len(data) // 2: len(data) // 2 + 32] = bytes(32)
    (tmp_path / "bad.mcap").write_bytes(bad)
    msg = _one_error_line(run_psm("learn", str(tmp_path / "bad.mcap")))
    assert msg.startswith(f"{tmp_path / 'bad.mcap'}: corrupt recording at byte "), msg


def test_command_path_names_nested_commands() -> None:
    import argparse

    from services.cli import build_parser, command_path

    parser = build_parser()
    assert command_path(parser, parser.parse_args(["serve", "router"])) == "psm serve router"
    assert command_path(parser, parser.parse_args(["camera", "synth"])) == "psm camera synth"
    assert command_path(parser, parser.parse_args(["learn", "x.csv"])) == "psm learn"
    assert command_path(parser, argparse.Namespace()) == "psm"


def test_headerless_csv_reads_every_row_as_a_sample(tmp_path: Path, reach_demo) -> None:
    t, X = reach_demo
    path = tmp_path / "noheader.csv"
    np.savetxt(path, np.column_stack([t, X]), delimiter=",")  # no header row
    r = run_psm("learn", str(path), "-o", str(tmp_path / "m.json"))
    assert r.returncode == 0, r.stderr
    assert f"from {len(t)} samples x 3 dims (x0, x1, x2)" in r.stdout  # no sample lost
    with_header = tmp_path / "header.csv"
    np.savetxt(with_header, np.column_stack([t, X]), delimiter=",", header="t,x,y,z", comments="")
    r = run_psm("learn", str(with_header), "-o", str(tmp_path / "m2.json"))
    assert r.returncode == 0 and f"from {len(t)} samples x 3 dims (x, y, z)" in r.stdout
    msg = _one_error_line(run_psm("learn", str(path), "--columns", "x"))
    assert msg == f"{path}: --columns needs a header row naming the columns (the first row is numbers)"


def test_a_demonstration_that_does_not_move_is_one_line(tmp_path: Path) -> None:
    t = np.linspace(0.0, 2.0, 1001)
    still = tmp_path / "still.csv"
    np.savetxt(still, np.column_stack([t, np.full((t.size, 3), 0.3)]), delimiter=",",
               header="t,x,y,z", comments="")
    msg = _one_error_line(run_psm("learn", str(still), "-o", str(tmp_path / "m.json")))
    assert msg == "demonstration does not move: max displacement 0 m over 2 s"
    assert not (tmp_path / "m.json").exists()
    # an MCAP of the arm at rest: one joint state repeated for 2 s of sim time
    from services.bus.log import read_log
    from services.bus.messages import ArmState, Keys, encode
    from services.bus.recorder import McapSink
    from services.learn_cli import DEMO_RECORDING

    first = next(m for _k, m, _s in read_log(DEMO_RECORDING) if isinstance(m, ArmState))
    rest = tmp_path / "rest.mcap"
    sink = McapSink(rest, metadata={"project_version": "test"})
    for i in range(1001):
        msg_i = ArmState()
        msg_i.CopyFrom(first)
        msg_i.tick, msg_i.sim_time_ns = i, i * 2_000_000
        msg_i.stamp_ns = msg_i.sim_time_ns
        payload, enc = encode(msg_i)
        sink.write(Keys().arm_state.key, enc, payload, 1_000 + i)
    sink.close()
    msg = _one_error_line(run_psm("learn", str(rest), "-o", str(tmp_path / "m.json")))
    assert msg == "demonstration does not move: max displacement 0 m over 2 s"

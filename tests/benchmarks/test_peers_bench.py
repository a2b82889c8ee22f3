"""The pure parts of the peer benchmark (benchmarks/peers.py): dataflow, statistics, ratios,
verdict and report on synthetic numbers. No timed assertions; dora is needed only for the
check that `dora validate` accepts the generated dataflow (skipped without it)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from benchmarks.peers import (
    TARGET_RATIO,
    VARIANTS,
    block_order,
    block_sizes,
    compare,
    dataflow_yaml,
    descendants,
    machine_busy_pct,
    render_markdown,
    summarize,
    verdict_text,
    write_report,
)


def _variant(p50: float, rate: float = 3000.0, cpu_us: float = 300.0) -> dict[str, Any]:
    n = 1000
    rtt = [p50] * n
    rtt[-1] = 3 * p50
    s = summarize(rtt, n / rate, {"a": cpu_us * n * 1e-6 / 2, "b": cpu_us * n * 1e-6 / 2})
    s["processes"] = ["a", "b"]
    s["other_variants_cpu_pct_during_blocks"] = 1.0
    return s


def _result(dora_p50: float, raw_p50: float, rt_p50: float,
            routed_p50: float | None = None) -> dict[str, Any]:
    """Peer-to-peer variants at ``raw_p50`` and ``rt_p50``; the routed ones 1.5× slower unless
    ``routed_p50`` (the runtime's) is given."""
    routed = 1.5 * rt_p50 if routed_p50 is None else routed_p50
    variants = {"dora": _variant(dora_p50, 2740), "raw": _variant(1.5 * raw_p50, 4660),
                "runtime": _variant(routed, 4000), "raw-p2p": _variant(raw_p50, 5000),
                "runtime-p2p": _variant(rt_p50, 4500)}
    return {
        "date_utc": "2026-01-01T00:00:00Z", "machine": "x86_64", "cpus": 2,
        "load_avg_start": "0.10, 0.10, 0.10", "load_avg_end": "0.20, 0.10, 0.10",
        "machine_busy_pct_before": 3.0, "machine_busy_pct_during": 60.0,
        "python": "3.11", "versions": {"dora-rs": "1.1.0", "dora-rs-cli": "1.1.0",
                                       "pyarrow": "1", "eclipse-zenoh": "1.10.2"},
        "params": {"round_trips": 1000, "warmup": 100, "per_block": 300},
        "variants": variants, "comparison": compare(variants),
        "dora_processes": ["dora run (daemon) (pid 1)"],
    }


def test_dataflow_names_both_nodes_wired_in_a_loop(tmp_path: Path) -> None:
    yaml = pytest.importorskip("yaml", reason="PyYAML (comes with the bench extra) parses the YAML")
    text = dataflow_yaml("127.0.0.1:4242", tmp_path / "ping.json", 60)
    flow = yaml.safe_load(text)
    nodes = {n["id"]: n for n in flow["nodes"]}
    assert set(nodes) == {"ping", "pong"}
    assert nodes["ping"]["inputs"] == {"pong": "pong/pong"}
    assert nodes["pong"]["inputs"] == {"ping": "ping/ping"}
    assert nodes["ping"]["outputs"] == ["ping"]
    assert nodes["pong"]["outputs"] == ["pong"]
    for role, node in nodes.items():
        assert node["path"] == "python"
        assert f"-m benchmarks.peers --dora-node {role}" in node["args"]
    assert "--control 127.0.0.1:4242" in nodes["ping"]["args"]
    assert str(tmp_path / "ping.json") in nodes["ping"]["args"]


def test_dora_validate_accepts_the_dataflow(tmp_path: Path) -> None:
    exe = shutil.which("dora", path=str(Path(sys.executable).parent) + os.pathsep
                       + os.environ.get("PATH", ""))
    if exe is None:
        pytest.skip("the dora CLI (dora-rs-cli, bench extra) is not installed")
    flow = tmp_path / "dataflow.yml"
    flow.write_text(dataflow_yaml("127.0.0.1:4242", tmp_path / "ping.json"))
    out = subprocess.run([exe, "validate", "--offline", str(flow)], capture_output=True,
                         text=True, timeout=60, check=False)
    assert out.returncode == 0, out.stdout + out.stderr


def test_blocks_and_rotating_order() -> None:
    assert block_sizes(900, 300) == [300, 300, 300]
    assert block_sizes(1000, 300) == [300, 300, 300, 100]
    assert block_sizes(5, 300) == [5]
    with pytest.raises(ValueError):
        block_sizes(0)
    n = len(VARIANTS)
    orders = [block_order(r) for r in range(n + 1)]
    assert orders[0] == list(VARIANTS)
    assert orders[n] == orders[0]
    assert [o[0] for o in orders[:n]] == list(VARIANTS)  # each variant goes first once a cycle


def test_summarize_rates_percentiles_and_cpu() -> None:
    rtt = [float(v) for v in range(1, 101)]  # 1..100 µs
    s = summarize(rtt, 0.5, {"router": 0.001, "ping": 0.002, "pong": 0.001}, wrong_replies=2)
    assert s["round_trips"] == 100
    assert s["round_trips_per_s"] == pytest.approx(200.0)
    assert s["p50_us"] in (50.0, 51.0)
    assert s["p99_us"] == 99.0
    assert s["max_us"] == 100.0
    assert s["cpu_per_round_trip_us"] == pytest.approx(40.0)
    assert s["cpu_per_round_trip_us_by_process"]["ping"] == pytest.approx(20.0)
    assert s["wrong_replies"] == 2
    with pytest.raises(ValueError):
        summarize([], 1.0, {})


def test_ratios_and_verdict() -> None:
    met = _result(dora_p50=342, raw_p50=191, rt_p50=200)["comparison"]
    assert met["runtime_p2p_over_dora_p50"] == pytest.approx(200 / 342)
    assert met["runtime_p2p_over_raw_p2p_p50"] == pytest.approx(200 / 191)
    assert met["runtime_over_dora_p50"] == pytest.approx(300 / 342)  # routed: reported only
    assert met["runtime_over_raw_p50"] == pytest.approx(300 / (1.5 * 191))
    assert met["target_runtime_over_dora_p50"] == TARGET_RATIO
    assert met["met"] is True
    assert "— **met**" in verdict_text(met)
    # The verdict is the deployed (peer-to-peer) runtime's, whatever the routed one measures.
    assert _result(dora_p50=342, raw_p50=191, rt_p50=200, routed_p50=100)["comparison"]["met"]
    assert not _result(dora_p50=342, raw_p50=191, rt_p50=300, routed_p50=100)["comparison"]["met"]
    missed = _result(dora_p50=342, raw_p50=191, rt_p50=300)["comparison"]
    assert missed["met"] is False
    assert "NOT met" in verdict_text(missed)
    edge = _result(dora_p50=100, raw_p50=50, rt_p50=70)["comparison"]
    assert edge["met"] is True  # ≤ target


def test_report_has_every_variant_and_the_verdict(tmp_path: Path) -> None:
    res = _result(dora_p50=342, raw_p50=191, rt_p50=300)
    md = render_markdown(res)
    for label in ("dora-rs", "raw zenoh-python via router", "project runtime via router",
                  "raw zenoh-python peer to peer", "project runtime peer to peer"):
        assert label in md
    assert "**0.88×**" in md  # runtime peer to peer / dora p50
    assert "NOT met" in md
    assert "2,740" in md and "342" in md  # the earlier figures beside this run's
    write_report(res, tmp_path)
    back = json.loads((tmp_path / "peers.json").read_text())
    assert back["comparison"]["met"] is False
    assert set(back["variants"]) == set(VARIANTS)
    assert (tmp_path / "peers.md").read_text() == md


def test_descendants_finds_a_child_process() -> None:
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        assert child.pid in descendants(os.getpid())
    finally:
        child.kill()
        child.wait(10)


def test_machine_busy_is_a_percentage() -> None:
    assert 0.0 <= machine_busy_pct(0.05) <= 100.0

"""What the benchmark reports record about the machine (benchmarks/host.py): the CPU model and
vector extensions read from /proc/cpuinfo (x86 and ARM layouts), numpy's SIMD dispatch, the
header line."""

from __future__ import annotations

from pathlib import Path

from benchmarks.host import _cpuinfo, host_info, host_line


def test_cpuinfo_gives_the_model_and_flags_of_x86_and_arm(tmp_path: Path) -> None:
    x86 = tmp_path / "x86"
    x86.write_text("processor\t: 0\nmodel name\t: Some Xeon\nflags\t\t: fpu sse4_2 avx2 avx512f\n\n"
                   "processor\t: 1\nmodel name\t: Other\nflags\t\t: fpu\n")
    assert _cpuinfo(x86) == ("Some Xeon", ["fpu", "sse4_2", "avx2", "avx512f"])
    arm = tmp_path / "arm"
    arm.write_text("processor\t: 0\nFeatures\t: fp asimd sve\nModel\t: Raspberry Pi 5\n")
    assert _cpuinfo(arm) == ("Raspberry Pi 5", ["fp", "asimd", "sve"])
    assert _cpuinfo(tmp_path / "missing") == ("", [])


def test_the_header_line_names_the_cpu_its_extensions_and_the_numeric_stack() -> None:
    info = {"cpu_model": "Some Xeon", "cpu_simd": ["avx2", "avx512f"], "numpy": "2.4.6",
            "numpy_simd": ["X86_V3", "X86_V4"], "scipy": "1.17.1"}
    assert host_line(info) == ("CPU Some Xeon (avx2, avx512f); numpy 2.4.6 "
                               "(SIMD dispatch: X86_V3, X86_V4), scipy 1.17.1")
    bare = host_line({"cpu_model": "x", "cpu_simd": [], "numpy": "1.26", "numpy_simd": []})
    assert bare == "CPU x (no vector extensions listed); numpy 1.26 (SIMD dispatch: baseline only)"
    real = host_info()
    assert real["cpus"] and real["numpy"] and real["cpu_model"]
    assert set(real["cpu_simd"]) <= set(_cpuinfo()[1])

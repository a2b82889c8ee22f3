"""``psm experiments`` and ``psm report``: run the experiments, turn results into a report.

    psm experiments --list                       # the experiments, in the order --all runs them
    psm experiments feeding cylinder --quick     # run two (fewer trials) into out/experiments/
    psm experiments --all --seed 1               # every one, then out/experiments/report.{md,html}
    psm report out/experiments                   # a report from result folders (no re-run)
    psm report out/run.mcap                      # a report of a recorded stack run

``psm experiments`` runs each named experiment with :func:`experiments.registry.run` (its folder
``<out>/<name>/`` gets ``result.json``, PNGs and MCAPs) under a progress bar, then writes the
report of the experiments it ran into ``<out>``. An unknown name (or an experiment whose module
is not installed) is one error line before anything runs. An experiment that fails is reported
with its traceback and the others still run; the exit code is then 1.

``psm report PATH ...``: each PATH is a result folder (with ``result.json``), a folder of result
folders, or a recording of a stack run (``.mcap``, :mod:`experiments.recording`). It writes
``report.md`` and ``report.html`` (with the PNGs) into ``--out``; the default is next to the
input: the result folder itself, the folder of results, or ``<dir>/<stem>-report/`` for
``<dir>/<stem>.mcap`` (several inputs: the folder they share).
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import sys
import time
import traceback
from pathlib import Path

__all__ = ["cmd_experiments", "cmd_report", "register"]

DEFAULT_OUT = Path("out/experiments")


def _known(name: str) -> bool:
    """Whether the experiment module of ``name`` can be imported (without importing it)."""
    from experiments.registry import EXPERIMENT_MODULES

    try:
        return importlib.util.find_spec(EXPERIMENT_MODULES[name]) is not None
    except ModuleNotFoundError:
        return False


def _selected(args: argparse.Namespace) -> list[str]:
    """The experiment names to run, checked: ValueError naming an unknown or missing one."""
    from experiments.registry import EXPERIMENT_MODULES

    if args.all and args.names:
        raise ValueError("give experiment names or --all, not both")
    if not args.all and not args.names:
        raise ValueError(f"name an experiment or give --all (known: {', '.join(EXPERIMENT_MODULES)})")
    names = list(EXPERIMENT_MODULES) if args.all else list(dict.fromkeys(args.names))
    for name in names:
        if name not in EXPERIMENT_MODULES:
            raise ValueError(f"no experiment {name!r}; known: {', '.join(EXPERIMENT_MODULES)}")
        if not _known(name):
            raise ValueError(f"experiment {name!r}: its module {EXPERIMENT_MODULES[name]} is not installed")
    return names


def cmd_experiments(args: argparse.Namespace) -> int:
    """``psm experiments``: see the module docstring."""
    from experiments.registry import EXPERIMENT_MODULES

    if args.list:
        for name, module in EXPERIMENT_MODULES.items():
            print(f"{name:<12} {module}{'' if _known(name) else '  (not installed)'}")
        return 0
    names = _selected(args)
    if args.seed < 0:
        raise ValueError(f"--seed must be >= 0, got {args.seed}")
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from experiments import registry
    from experiments.report import ReportEntry, write_report

    out_root = Path(args.out)
    console = Console(stderr=True)
    entries: list[ReportEntry] = []
    failed: list[str] = []
    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
    for name in names:
        t0 = time.perf_counter()
        with Progress(*columns, console=console, transient=True) as bar:
            task = bar.add_task(name, total=None)

            def progress(done: int, total: int, label: str, _task: object = task, _name: str = name) -> None:
                bar.update(_task, completed=done, total=max(total, 1),
                           description=f"{_name}: {label}" if label else _name)

            try:
                res = registry.run(name, out_root, seed=args.seed, quick=args.quick, progress=progress)
            except KeyboardInterrupt:
                raise
            except Exception as exc:  # an experiment's bug: report it, run the others
                bar.stop()
                traceback.print_exc()
                print(f"psm experiments: {name} failed: {type(exc).__name__}: {exc}", file=sys.stderr)
                failed.append(name)
                continue
        ok = sum(1 for v in res.verdicts.values() if v.get("ok"))
        print(f"{name}: {ok}/{len(res.verdicts)} verdicts pass, {time.perf_counter() - t0:.1f} s "
              f"-> {out_root / name}")
        entries.append(ReportEntry(res, out_root / name))
    if entries:
        md, page = write_report(entries, out_root)
        print(f"report: {md} and {page}")
    if failed:
        print(f"psm experiments: failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


def default_out(path: Path) -> Path:
    """Where ``psm report PATH`` writes by default (see the module docstring)."""
    if path.suffix.lower() == ".mcap":
        return path.parent / f"{path.stem}-report"
    return path


def cmd_report(args: argparse.Namespace) -> int:
    """``psm report``: see the module docstring."""
    from experiments.recording import recording_result
    from experiments.report import ReportEntry, find_results, write_report
    from experiments.result import ExperimentResult

    paths = [Path(p) for p in args.paths]
    for p in paths:
        if not p.exists():
            raise FileNotFoundError(2, "No such file or directory", str(p))
    if args.out:
        out = Path(args.out)
    elif len(paths) == 1:
        out = default_out(paths[0])
    else:
        out = Path(os.path.commonpath([str(default_out(p).resolve().parent) for p in paths]))
    entries: list[ReportEntry] = []
    for p in paths:
        if p.is_file():
            if p.suffix.lower() != ".mcap":
                raise ValueError(f"{p}: not a result folder or a recording (.mcap)")
            folder = out / p.stem
            res = recording_result(
                p, folder, task_file=Path(args.task) if args.task else None,
                cache_dir=Path(args.cache_dir) if args.cache_dir else None,
            )
            res.write(folder)
            entries.append(ReportEntry(res, folder))
            continue
        for folder in find_results(p):
            entries.append(ReportEntry(ExperimentResult.read(folder), folder))
    title = args.title or (entries[0].result.title if len(entries) == 1 else "Experiments")
    md, page = write_report(entries, out, title)
    print(f"report: {md} and {page}")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``experiments`` and ``report`` to the ``psm`` command line."""
    p = subparsers.add_parser("experiments", help="run the paper's experiments and write their report")
    p.add_argument("names", nargs="*", metavar="NAME", help="experiments to run (see --list)")
    p.add_argument("--all", action="store_true", help="run every experiment, in the registry's order")
    p.add_argument("--out", default=str(DEFAULT_OUT), metavar="DIR",
                   help=f"results root: DIR/<name>/ per experiment, DIR/report.* (default {DEFAULT_OUT})")
    p.add_argument("--seed", type=int, default=0, help="random seed of the runs (default 0)")
    p.add_argument("--quick", action="store_true", help="fewer trials, the same code (smoke runs)")
    p.add_argument("--list", action="store_true", help="list the experiments and exit")
    p.set_defaults(func=cmd_experiments)

    p = subparsers.add_parser("report", help="Markdown + HTML report of results or of a recorded run")
    p.add_argument("paths", nargs="+", metavar="PATH",
                   help="a result folder, a folder of result folders, or a stack recording (.mcap)")
    p.add_argument("--out", metavar="DIR", help="report folder (default: next to the input)")
    p.add_argument("--title", help="the report's title")
    p.add_argument("--task", metavar="FILE.toml",
                   help="recordings: the task the planner ran (default configs/feeding.toml)")
    p.add_argument("--cache-dir", default="out/models", metavar="DIR",
                   help="recordings: the planner's model cache (default out/models; '' learns anew)")
    p.set_defaults(func=cmd_report)

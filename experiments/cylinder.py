"""Experiment 3 of the paper: rolling a cylinder into a basket, PSM against DMPs (paper §IV-D, Fig. 10).

Every method of :mod:`experiments.methods` learns the strike demonstration
(``data/demos/cylinder_strike.mcap``: a slow approach, a touch of the cylinder at y = −0.10 m at
~0.05 m/s, a push accelerating to ~0.5 m/s along +y until y ≈ +0.10 m, a stop) and is rolled out at
the demonstration's dt from several starts and with the arm held still for a moment on the way
(a temporal perturbation). Each end-effector path strikes the simulated cylinder of
:mod:`experiments.rolling`; the cylinder rolls to the table's edge and lands in the basket or not.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from experiments import rolling
from experiments.methods import (
    METHODS,
    PSM_KEYS,
    Hold,
    fit_method,
    load_arm_demo,
    run_method,
    write_tracks_mcap,
)
from experiments.registry import Experiment, Progress
from experiments.result import Column, ExperimentResult, Figure, Headline

DEMO = "cylinder_strike"
#: y of the cylinder's back face (the meeting point) and of the end of the demonstrated push
#: (where the demonstration runs at ~0.5 m/s), m.
MEET_Y = -0.10
STRIKE_Y = 0.10
#: Starts [m] (the demonstration's first, then six others: farther, closer, lower, higher, beside).
STARTS: dict[str, tuple[float, float, float]] = {
    "demo start": (0.45, -0.35, 0.15),
    "farther": (0.45, -0.45, 0.15),
    "closer": (0.45, -0.25, 0.15),
    "closer, lower": (0.45, -0.20, 0.08),
    "higher": (0.45, -0.35, 0.25),
    "beside, closer": (0.40, -0.30, 0.12),
    "beside, farther, higher": (0.50, -0.42, 0.20),
}
#: Temporal perturbations from the demonstration's start: held still for ``duration`` s at ``t0`` s.
HOLDS: dict[str, tuple[float, float]] = {
    "held 0.4 s at 1.0 s": (1.0, 0.4),
    "held 0.4 s at 2.0 s": (2.0, 0.4),
}
QUICK_CONDITIONS = ("demo start", "closer", "held 0.4 s at 1.0 s")
#: The scene: a beech cylinder (700 kg/m³, r 4 cm, 12 cm long: 0.42 kg) on a cloth-covered table
#: (c_rr 0.02, μ 0.4), the table's edge at y = 0.90 m, a basket 2 cm beyond it, 15 cm wide, its
#: rim 30 cm below the table top; restitution 0.3 (rubber finger pads on wood).
SCENE_CYLINDER = rolling.Cylinder(radius=0.04, length=0.12, mass=0.42, rolling_resistance=0.02, friction=0.4)
SCENE_BASKET = rolling.Basket(edge_y=0.90, near_y=0.92, far_y=1.07, rim_z=-0.30)
RESTITUTION = 0.3
EXTRA_TIME = 1.0  # s of rollout after the demonstration's duration
SENSITIVITY = (0.75, 1.0, 1.25)  # factors on c_rr for the window table


def effector_apparent_mass(demo_path: Path, y: float = MEET_Y) -> float:
    """The Panda hand's apparent mass along +y [kg] at the demonstration's sample nearest ``y``:
    ``1 / (e_yᵀ J M⁻¹ Jᵀ e_y)`` (J the hand's linear Jacobian, M the joint-space mass matrix of the
    URDF's links; the motors' rotor inertia is not in the URDF)."""
    import pinocchio as pin

    from services.bus.log import read_log
    from services.bus.messages import ArmState
    from services.robot.model import RobotModel

    robot = RobotModel.load()
    Q = np.array([list(m.q) for _, m, _ in read_log(demo_path) if isinstance(m, ArmState)])
    X = robot.fk_positions(Q)
    q = Q[int(np.argmin(np.abs(X[:, 1] - y)))]
    robot.update(q, np.zeros(robot.n))
    J = robot.jacobian()[:3]
    M = pin.crba(robot.model, robot.data, q)
    M = np.triu(M) + np.triu(M, 1).T
    lam_inv = J @ np.linalg.solve(M, J.T)
    return float(1.0 / lam_inv[1, 1])


def _scene(effector_mass: float, c_rr_factor: float = 1.0) -> rolling.StrikeScene:
    cyl = SCENE_CYLINDER
    if c_rr_factor != 1.0:
        cyl = rolling.Cylinder(
            cyl.radius, cyl.length, cyl.mass, cyl.rolling_resistance * c_rr_factor, cyl.friction
        )
    return rolling.StrikeScene(
        cylinder=cyl,
        basket=SCENE_BASKET,
        start=(0.45, MEET_Y + cyl.radius),
        effector_mass=effector_mass,
        restitution=RESTITUTION,
    )


def _speed_at(t: np.ndarray, x: np.ndarray, v: np.ndarray, y: float) -> float | None:
    """v_y [m/s] where the path first crosses ``y`` (linear interpolation), None if never."""
    above = np.nonzero(x[:, 1] >= y)[0]
    if len(above) == 0 or above[0] == 0:
        return None
    i = above[0]
    f = (y - x[i - 1, 1]) / (x[i, 1] - x[i - 1, 1])
    return float(v[i - 1, 1] + f * (v[i, 1] - v[i - 1, 1]))


def strike_metrics(sim: rolling.StrikeResult, t: np.ndarray, x: np.ndarray, v: np.ndarray) -> dict[str, Any]:
    """The per-rollout metrics (see docs/experiments.md, *Cylinder rolling*)."""
    met: dict[str, Any] = {
        "v_at_meet_y": _speed_at(t, x, v, MEET_Y),
        "v_at_strike_y": _speed_at(t, x, v, STRIKE_Y),
        "outcome": sim.outcome,
        "landed": sim.landed,
        "v_release": sim.v_release if sim.meet_index is not None else None,
        "v_edge": sim.v_edge,
        "contacts": len(sim.contacts),
    }
    if sim.meet_index is not None:
        i = sim.meet_index
        met.update(
            v_meet=float(v[i, 1]),
            meet_t=float(t[i]),
            meet_y=float(x[i, 1]),
            meet_z=float(x[i, 2]),
            meet_x=float(x[i, 0]),
        )
        span = slice(sim.meet_index, sim.release_index + 1)
        met["v_peak_contact"] = float(v[span, 1].max())
        met["y_release"] = sim.y_release
    return met


def run(out_dir: Path, *, seed: int, quick: bool, progress: Progress) -> ExperimentResult:
    """Run the experiment into ``out_dir`` (see the module docstring). ``seed`` is unused: the
    experiment is deterministic."""
    import matplotlib

    matplotlib.use("Agg")
    demo = load_arm_demo(DEMO)
    demo_v = np.gradient(demo.x, demo.t, axis=0)
    m_e = effector_apparent_mass(Path(__file__).resolve().parents[1] / "data" / "demos" / f"{DEMO}.mcap")
    scene = _scene(m_e)
    conditions: dict[str, tuple[tuple[float, float, float], tuple[float, float] | None]] = {
        **{k: (s, None) for k, s in STARTS.items()},
        **{k: (STARTS["demo start"], h) for k, h in HOLDS.items()},
    }
    if quick:
        conditions = {k: conditions[k] for k in QUICK_CONDITIONS}
    duration = demo.duration + EXTRA_TIME

    demo_sim = rolling.simulate_strike(scene, demo.t, demo.x, demo_v)
    demo_met = strike_metrics(demo_sim, demo.t, demo.x, demo_v)
    v_lo, v_hi = rolling.landing_window(scene, demo_sim.y_release)
    res = ExperimentResult(
        name="cylinder",
        title=EXPERIMENT.title,
        seed=seed,
        description=EXPERIMENT.description,
        config={
            "demo": f"data/demos/{DEMO}.mcap",
            "dt_s": demo.dt,
            "rollout_s": duration,
            "methods": {k: m.label for k, m in METHODS.items()},
            "starts_m": {k: list(s) for k, s in STARTS.items() if k in conditions},
            "holds_s": {k: list(h) for k, h in HOLDS.items() if k in conditions},
            "cylinder": vars(scene.cylinder)
            | {"rolling_deceleration_m_s2": scene.cylinder.rolling_deceleration},
            "basket": vars(scene.basket),
            "effector_mass_kg": m_e,
            "restitution": scene.restitution,
            "meet_y_m": MEET_Y,
            "strike_y_m": STRIKE_Y,
            "quick": quick,
        },
    )
    total = len(METHODS) * len(conditions)
    done = 0
    fitted = {k: fit_method(k, demo) for k in METHODS}
    rows: list[dict[str, Any]] = []
    runs: dict[tuple[str, str], Any] = {}
    for key in METHODS:
        for cond, (x0, hold) in conditions.items():
            disturbance = Hold(*hold) if hold else None
            r = run_method(fitted[key], np.array(x0), duration, disturbance=disturbance)
            sim = rolling.simulate_strike(scene, r.t, r.x, r.v)
            met = strike_metrics(sim, r.t, r.x, r.v)
            met.update(
                method=key, condition=cond, final_error_mm=1e3 * float(np.linalg.norm(r.x[-1] - demo.x[-1]))
            )
            rows.append(met)
            runs[(key, cond)] = (r, sim)
            done += 1
            progress(done, total, f"{METHODS[key].label}, {cond}")

    # ---- tables
    def ratio(a: float | None, b: float | None) -> float | None:
        return None if a is None or b is None or b == 0 else a / b

    tab = res.table(
        "Strikes per method and condition",
        [
            Column("method", "method"),
            Column("condition", "condition"),
            Column("v_meet", "v_y at the meeting", "m/s"),
            Column("meet_y", "meeting y", "m"),
            Column("meet_z", "meeting z", "m"),
            Column("v_at_strike_y", "v_y at y = +0.10 m", "m/s"),
            Column("strike_ratio", "÷ demo", ""),
            Column("v_release", "cylinder release speed", "m/s"),
            Column("release_ratio", "÷ demo", ""),
            Column("v_edge", "speed at the edge", "m/s"),
            Column("outcome", "outcome"),
            Column("landed", "in the basket"),
            Column("final_error_mm", "final error to the goal", "mm", 1),
        ],
        note=(
            f"Demonstration: v_y {demo_met['v_meet']:.3f} m/s at the meeting, "
            f"{demo_met['v_at_strike_y']:.3f} m/s at y = +0.10 m, release {demo_sim.v_release:.3f} m/s, "
            f"{demo_sim.outcome}. Landing window of the release speed at y = {demo_sim.y_release:.3f} m: "
            f"{v_lo:.3f}–{v_hi:.3f} m/s."
        ),
    )
    tab.add(
        method="demo",
        condition="demonstration",
        v_meet=demo_met["v_meet"],
        meet_y=demo_met["meet_y"],
        meet_z=demo_met["meet_z"],
        v_at_strike_y=demo_met["v_at_strike_y"],
        strike_ratio=1.0,
        v_release=demo_sim.v_release,
        release_ratio=1.0,
        v_edge=demo_sim.v_edge,
        outcome=demo_sim.outcome,
        landed=demo_sim.landed,
        final_error_mm=0.0,
    )
    for m in rows:
        tab.add(
            method=METHODS[m["method"]].label,
            condition=m["condition"],
            v_meet=m.get("v_meet"),
            meet_y=m.get("meet_y"),
            meet_z=m.get("meet_z"),
            v_at_strike_y=m["v_at_strike_y"],
            strike_ratio=ratio(m["v_at_strike_y"], demo_met["v_at_strike_y"]),
            v_release=m["v_release"],
            release_ratio=ratio(m["v_release"], demo_sim.v_release),
            v_edge=m["v_edge"],
            outcome=m["outcome"],
            landed=m["landed"],
            final_error_mm=m["final_error_mm"],
        )

    summ = res.table(
        "Per method",
        [
            Column("method", "method"),
            Column("landed", "landed", "of runs"),
            Column("landed_starts", "landed from the starts", "of starts"),
            Column("landed_holds", "landed when held", "of holds"),
            Column("release_min", "release speed min", "m/s"),
            Column("release_max", "max", "m/s"),
            Column("worst_release_dev", "worst |release ÷ demo − 1|", "%", 1),
            Column("worst_strike_dev", "worst |v(+0.10) ÷ demo − 1|", "%", 1),
            Column("v_meet_max", "largest meeting speed", "m/s"),
        ],
    )
    per: dict[str, dict[str, Any]] = {}
    for key, meth in METHODS.items():
        mine = [m for m in rows if m["method"] == key]
        st = [m for m in mine if m["condition"] in STARTS]
        ho = [m for m in mine if m["condition"] in HOLDS]
        rel = [m["v_release"] for m in mine if m["v_release"] is not None]
        strike = [m["v_at_strike_y"] for m in mine if m["v_at_strike_y"] is not None]
        meets = [m["v_meet"] for m in mine if m.get("v_meet") is not None]
        per[key] = {
            "landed": sum(m["landed"] for m in mine),
            "n": len(mine),
            "landed_starts": sum(m["landed"] for m in st),
            "n_starts": len(st),
            "worst_release": max((abs(v / demo_sim.v_release - 1) for v in rel), default=None),
            "worst_strike": max((abs(v / demo_met["v_at_strike_y"] - 1) for v in strike), default=None),
            "worst_strike_starts": max(
                (abs(m["v_at_strike_y"] / demo_met["v_at_strike_y"] - 1) for m in st
                 if m["v_at_strike_y"] is not None),
                default=None,
            ),
            "struck_starts": sum(m["v_at_strike_y"] is not None for m in st),
            "struck": len(strike),
        }
        summ.add(
            method=meth.label,
            landed=f"{per[key]['landed']}/{len(mine)}",
            landed_starts=f"{per[key]['landed_starts']}/{len(st)}",
            landed_holds=f"{sum(m['landed'] for m in ho)}/{len(ho)}",
            release_min=min(rel, default=None),
            release_max=max(rel, default=None),
            worst_release_dev=None if per[key]["worst_release"] is None else 100 * per[key]["worst_release"],
            worst_strike_dev=None if per[key]["worst_strike"] is None else 100 * per[key]["worst_strike"],
            v_meet_max=max(meets, default=None),
        )

    win = res.table(
        "Landing window of the release speed",
        [
            Column("c_rr", "rolling resistance c_rr"),
            Column("a_rr", "deceleration", "m/s²"),
            Column("v_lo", "lowest landing speed", "m/s"),
            Column("v_hi", "highest", "m/s"),
            Column("at_0_4", "outcome at 0.40 m/s"),
            Column("at_demo", "outcome at the demo's release"),
        ],
        note=(
            f"Release at the demonstration's release point y = {demo_sim.y_release:.3f} m; the lower "
            "bound is reaching the edge (sqrt(2 a_rr d)), the upper one the far rim."
        ),
    )
    for f in SENSITIVITY:
        sc = _scene(m_e, f)
        lo, hi = rolling.landing_window(sc, demo_sim.y_release)
        win.add(
            c_rr=sc.cylinder.rolling_resistance,
            a_rr=sc.cylinder.rolling_deceleration,
            v_lo=lo,
            v_hi=hi,
            at_0_4=rolling.outcome_for_release(sc, demo_sim.y_release, 0.4)[0],
            at_demo=rolling.outcome_for_release(sc, demo_sim.y_release, demo_sim.v_release)[0],
        )

    # ---- headline and verdicts
    at04 = rolling.outcome_for_release(scene, demo_sim.y_release, 0.4)[0]
    res.headline["window"] = Headline(
        "landing window (release speed)",
        f"{v_lo:.3f}–{v_hi:.3f}",
        "m/s",
        f"demo releases at {demo_sim.v_release:.3f} m/s; 0.40 m/s: {at04}",
    )
    for key in METHODS:
        p = per[key]
        res.headline[f"landed_{key}"] = Headline(
            f"{METHODS[key].label} landed",
            f"{p['landed']}/{p['n']}",
            "runs",
            "worst release "
            + ("n/a" if p["worst_release"] is None else f"{100 * p['worst_release']:.1f} % off the demo"),
        )
    res.verdict(
        "demo_lands",
        demo_sim.landed,
        "the demonstrated strike lands the cylinder",
        f"{demo_sim.outcome} (release {demo_sim.v_release:.3f} m/s)",
    )
    res.verdict("slow_fails", at04 != rolling.LANDED, "a 0.40 m/s release does not land (paper's DMP)", at04)
    res.verdict(
        "demo_inside_window",
        v_lo is not None and v_lo < demo_sim.v_release < v_hi,
        "the demonstrated release lies inside the landing window",
        f"{demo_sim.v_release:.3f} in {v_lo:.3f}–{v_hi:.3f} m/s "
        f"({100 * (demo_sim.v_release / v_lo - 1):.0f} % above its lower end)",
    )
    psm = per["psm"]
    res.verdict(
        "psm_lands_all",
        psm["landed"] == psm["n"],
        "PSM lands the cylinder in every condition",
        f"{psm['landed']}/{psm['n']}",
    )
    res.verdict(
        "psm_strike_2pct",
        psm["struck"] == psm["n"] and psm["worst_strike"] is not None and psm["worst_strike"] <= 0.02,
        "PSM's v_y at y = +0.10 m within 2 % of the demonstration's in every condition",
        f"{psm['struck']}/{psm['n']} strike, worst "
        + ("n/a" if psm["worst_strike"] is None else f"{100 * psm['worst_strike']:.1f} %"),
    )
    dmp_fail = [
        f"{METHODS[k].label}: {per[k]['n'] - per[k]['landed']}"
        for k in METHODS
        if k not in PSM_KEYS and per[k]["landed"] < per[k]["n"]
    ]
    res.verdict(
        "paper_dmp_failure",
        bool(dmp_fail),
        "a DMP fails the task in some condition (paper: DMP 0.4 m/s)",
        "failures " + (", ".join(dmp_fail) if dmp_fail else "none"),
    )

    # ---- figures and recording
    _plot_phase(out_dir / "cylinder_phase.png", demo, demo_v, runs, conditions)
    _plot_paths(out_dir / "cylinder_paths.png", scene, demo_sim, runs)
    _plot_release(out_dir / "cylinder_release.png", rows, demo_sim.v_release, v_lo, v_hi, conditions)
    res.figures += [
        Figure(
            "cylinder_phase.png",
            "Phase plots (position–velocity) of x, y, z per method against the "
            "demonstration (black); dashed lines: the meeting (y = −0.10 m) and the push's end (+0.10 m)",
        ),
        Figure("cylinder_paths.png", "The cylinder's centre from rest to the basket (side view), per method"),
        Figure("cylinder_release.png", "Release speed per method and condition; shaded: the landing window"),
    ]
    tracks = {"psm/experiments/cylinder/demo/effector": (demo.t, demo.x)}
    for (key, cond), (r, sim) in runs.items():
        cid = _slug(cond)
        tracks[f"psm/experiments/cylinder/{key}/{cid}/effector"] = (r.t, r.x)
        ok = np.isfinite(sim.y)
        tracks[f"psm/experiments/cylinder/{key}/{cid}/cylinder"] = (
            r.t[ok],
            np.column_stack(
                [np.full(ok.sum(), scene.start[0]), sim.y[ok], np.full(ok.sum(), scene.cylinder.radius)]
            ),
        )
    write_tracks_mcap(
        out_dir / "cylinder_rollouts.mcap", tracks, {"experiment": "cylinder", "seed": str(seed)}
    )
    res.recordings.append("cylinder_rollouts.mcap")
    return res


def _slug(s: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in s).strip("_").replace("__", "_")


def _plot_phase(
    path: Path, demo: Any, demo_v: np.ndarray, runs: dict[tuple[str, str], Any], conditions: dict[str, Any]
) -> None:
    import matplotlib.pyplot as plt

    cmap = plt.get_cmap("viridis")
    colors = {c: cmap(i / max(len(conditions) - 1, 1)) for i, c in enumerate(conditions)}
    fig, axes = plt.subplots(len(METHODS), 3, figsize=(13, 2.6 * len(METHODS)), squeeze=False)
    for row, (key, meth) in enumerate(METHODS.items()):
        for d, name in enumerate("xyz"):
            ax = axes[row, d]
            for cond in conditions:
                r, _ = runs[(key, cond)]
                ax.plot(r.x[:, d], r.v[:, d], color=colors[cond], lw=1.0, label=cond)
            ax.plot(demo.x[:, d], demo_v[:, d], color="black", lw=1.6, label="demonstration")
            if name == "y":
                for y in (MEET_Y, STRIKE_Y):
                    ax.axvline(y, color="grey", ls="--", lw=0.8)
            ax.set_xlabel(f"{name} [m]")
            ax.set_ylabel(f"v_{name} [m/s]")
            ax.set_title(f"{meth.label}: {name}", fontsize=9)
            ax.grid(alpha=0.3)
    axes[0, 2].legend(fontsize=6, loc="best")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _plot_paths(
    path: Path, scene: rolling.StrikeScene, demo_sim: rolling.StrikeResult, runs: dict[tuple[str, str], Any]
) -> None:
    import matplotlib.pyplot as plt

    b, r = scene.basket, scene.cylinder.radius
    fig, axes = plt.subplots(1, 2, figsize=(12, 4), gridspec_kw={"width_ratios": [2, 1]})
    for ax in axes:
        ax.fill_between([-0.4, b.edge_y], [-0.02, -0.02], [0, 0], color="0.6", label="table")
        ax.plot(
            [b.near_y, b.near_y, b.far_y, b.far_y],
            [b.rim_z, b.rim_z - 0.1, b.rim_z - 0.1, b.rim_z],
            color="saddlebrown",
            lw=2,
            label="basket",
        )
        seen = set()
        for (key, _cond), (_r, sim) in runs.items():
            lab = None if key in seen else METHODS[key].label
            seen.add(key)
            ax.plot(sim.path[:, 0], sim.path[:, 1], color=METHODS[key].color, lw=0.9, alpha=0.8, label=lab)
        ax.plot(
            demo_sim.path[:, 0], demo_sim.path[:, 1], color="black", lw=1.4, ls="--", label="demonstration"
        )
        ax.set_xlabel("y [m]")
        ax.set_ylabel("z of the centre [m]")
        ax.grid(alpha=0.3)
    axes[0].set_title("The cylinder's centre (side view)")
    axes[1].set_xlim(b.edge_y - 0.25, b.far_y + 0.05)
    axes[1].set_ylim(b.rim_z - 0.12, 3 * r)
    axes[1].set_title("At the edge and the basket")
    axes[0].legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _plot_release(
    path: Path,
    rows: list[dict[str, Any]],
    v_demo: float,
    v_lo: float | None,
    v_hi: float | None,
    conditions: dict[str, Any],
) -> None:
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(10, 4))
    if v_lo is not None and v_hi is not None:
        ax.axhspan(v_lo, v_hi, color="tab:green", alpha=0.15, label="landing window")
    ax.axhline(v_demo, color="black", lw=1, label="demonstration")
    ax.axhline(0.4, color="grey", ls=":", lw=1, label="0.40 m/s (paper's DMP)")
    conds = list(conditions)
    width = 0.8 / len(METHODS)
    for j, (key, meth) in enumerate(METHODS.items()):
        vals = [
            next((m["v_release"] or 0.0) for m in rows if m["method"] == key and m["condition"] == c)
            for c in conds
        ]
        ax.bar(
            np.arange(len(conds)) + (j - (len(METHODS) - 1) / 2) * width,
            vals,
            width,
            color=meth.color,
            label=meth.label,
        )
    ax.set_xticks(np.arange(len(conds)))
    ax.set_xticklabels(conds, rotation=20, fontsize=7, ha="right")
    ax.set_ylabel("release speed of the cylinder [m/s]")
    lo = min([m["v_release"] or 0.0 for m in rows] + [0.4])
    ax.set_ylim(max(0.0, lo - 0.1), None)
    ax.legend(fontsize=7, ncol=3)
    ax.grid(alpha=0.3, axis="y")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


EXPERIMENT = Experiment(
    name="cylinder",
    title="Cylinder rolling: PSM against DMP (paper §IV-D, Fig. 10)",
    run=run,
    description=(
        "PSM, DMP-10, DMP-50, an amplitude-scaled DMP-50 and DMPWithFinalVelocity learn the strike "
        "demonstration; from seven starts and with the arm held on the way, each path strikes a "
        "simulated rolling cylinder (impulse, rolling resistance, edge and ballistic flight) that must "
        "land in a basket at the table's end."
    ),
)

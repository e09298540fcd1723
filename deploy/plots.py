"""PNG figures (matplotlib, non-interactive backend)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def plot_replay_error(res, path: Path) -> None:
    """Horizontal error of the antenna position over time, outages shaded."""
    t0 = res.t0
    fig, ax = plt.subplots(figsize=(11, 4))
    for s, f in res.outages:
        ax.axvspan(s - t0, f - t0, color="tab:orange", alpha=0.2, lw=0)
    ax.plot(res.t - t0, res.h_err, lw=0.8, color="tab:blue", label="horizontal error")
    if len(res.trajectory):
        sig = (res.trajectory[:, 10] ** 2 + res.trajectory[:, 11] ** 2) ** 0.5
        ax.plot(res.trajectory[:, 0] - t0, sig, lw=0.8, color="tab:gray", ls="--",
                label="reported horizontal σ")
    ax.set_xlabel("time since first GNSS epoch [s]")
    ax.set_ylabel("error [m]")
    ax.set_yscale("symlog", linthresh=0.1)
    m = res.metrics
    ax.set_title(f"SP replay: outage RMS {m['outage_h_rms_m']:.2f} m, end mean {m['outage_h_end_mean_m']:.2f} m, "
                 f"max {m['outage_h_max_m']:.2f} m (shaded: GNSS withheld)")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_scenario(truth, path: Path, events: dict[str, float] | None = None) -> None:
    """Map of a scenario: lanes, lane lines, stop lines, trajectories coloured by vehicle,
    stop events marked."""
    import numpy as np

    from agent.nav import earth
    from hw_emulation.geometry import offset_polyline

    scn = truth.scenario
    fig, ax = plt.subplots(figsize=(8, 8))
    for ln in scn.lanes.values():
        c = ln.centerline
        ax.plot(c[:, 1], c[:, 0], color="0.85", lw=6, solid_capstyle="butt", zorder=1)
        left = offset_polyline(c, -ln.width / 2)
        ax.plot(left[:, 1], left[:, 0], color="0.6", lw=0.6, ls="--", zorder=2)
        if ln.stop_line:
            d = c[-1] - c[-2]
            d = d / np.hypot(*d)
            r = np.array([-d[1], d[0]]) * ln.width / 2
            a, b = c[-1] - r, c[-1] + r
            ax.plot([a[1], b[1]], [a[0], b[0]], color="k", lw=2.0, zorder=3)
    cmap = plt.get_cmap("tab10" if len(truth.vehicles) <= 10 else "tab20")
    for i, (vid, vt) in enumerate(truth.vehicles.items()):
        llh = vt.truth.llh
        ne = np.array([earth.ned_offset(*p, *scn.origin_llh)[:2] for p in llh[::20]])
        col = cmap(i % cmap.N)
        ax.plot(ne[:, 1], ne[:, 0], color=col, lw=1.5, label=vid, zorder=4)
        ax.plot(ne[0, 1], ne[0, 0], "o", color=col, ms=4, zorder=5)
        fs = np.flatnonzero(vt.first_stopped[::20])
        st = np.flatnonzero(vt.stopped[::20])
        if st.size:
            ax.plot(ne[st[0], 1], ne[st[0], 0], "s", color=col, mec="k", ms=7, zorder=6)
        if fs.size:
            ax.plot(ne[fs[0], 1], ne[fs[0], 0], "*", color=col, mec="k", ms=13, zorder=7)
    ax.set_aspect("equal")
    ax.set_xlabel("east [m]")
    ax.set_ylabel("north [m]")
    lim = 120.0
    ax.set_xlim(-lim, lim)
    ax.set_ylim(-lim, lim)
    title = f"{scn.name}: ■ stopped, ★ first stopped"
    if events:
        title += "\n" + ", ".join(f"{k}={v:.1f}s" for k, v in events.items())
    ax.set_title(title, fontsize=9)
    ax.legend(loc="upper left", fontsize=8, ncol=2)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_run_errors(series: dict, windows: dict, methods, path: Path, title: str, sigma: dict | None = None,
                    bound=None, faults=None) -> None:
    """Horizontal error over time per vehicle (rows) and method (colours), like the paper's
    Fig. 9/11; evaluation windows shaded. Optional: each method's reported horizontal σ
    (``sigma[(vehicle, method)]``, dotted) and the posterior CRLB (:class:`deploy.bound.Bound`,
    dashed)."""
    vehicles = sorted({v for v, _ in series})
    fig, axes = plt.subplots(len(vehicles), 1, figsize=(10, 2.6 * len(vehicles)), sharex=True, squeeze=False)
    colours = {"SP": "tab:gray", "SL-SP": "tab:red", "CP": "tab:blue", "SL-CP": "tab:green"}
    for ax, vid in zip(axes[:, 0], vehicles):
        for i, (w, (a, b)) in enumerate(windows.items()):
            ax.axvspan(a, b, color="tab:orange", alpha=0.06 + 0.04 * (i % 2), lw=0)
        for f in faults or []:  # fault windows hatched (a kill is a line)
            if not f.vehicles or vid in f.vehicles:
                if f.end > f.start:
                    ax.axvspan(f.start, f.end, facecolor="none", edgecolor="tab:red", hatch="//", lw=0.5, alpha=0.6)
                else:
                    ax.axvline(f.start, color="tab:red", lw=1.0, ls="-.")
                ax.text(f.start, 1.0, f.kind, transform=ax.get_xaxis_transform(), fontsize=6, color="tab:red",
                        va="bottom")
        for m in methods:
            ts, eh = series.get((vid, m), (None, None))
            if ts is not None and len(ts):
                ax.plot(ts, eh[:, 0], lw=0.9, color=colours.get(m), label=m)
                if sigma is not None and (vid, m) in sigma:
                    ax.plot(ts, sigma[(vid, m)], lw=0.7, ls=":", color=colours.get(m))
                if bound is not None and (m, vid) in bound.cov:
                    ax.plot(bound.t, bound.sigma_h(m, vid), lw=0.8, ls="--", color=colours.get(m), alpha=0.7)
        ax.set_ylabel(f"{vid} error [m]")
        ax.set_yscale("symlog", linthresh=0.5)
        ax.grid(alpha=0.3)
    axes[0, 0].legend(loc="upper right", ncol=len(methods), fontsize=8,
                      title="solid: error, dotted: reported σ, dashed: bound" if bound is not None else None,
                      title_fontsize=7)
    axes[-1, 0].set_xlabel("time [s]")
    axes[0, 0].set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def plot_bound(bound, vehicles, methods, path: Path, title: str) -> None:
    """The posterior CRLB over time per vehicle (rows) and method (colours)."""
    fig, axes = plt.subplots(len(vehicles), 1, figsize=(10, 2.2 * len(vehicles)), sharex=True, squeeze=False)
    colours = {"SP": "tab:gray", "SL-SP": "tab:red", "CP": "tab:blue", "SL-CP": "tab:green"}
    for ax, vid in zip(axes[:, 0], vehicles):
        for m in methods:
            ax.plot(bound.t, bound.sigma_h(m, vid), lw=0.9, color=colours.get(m), label=m)
        ax.set_ylabel(f"{vid} σ [m]")
        ax.set_yscale("log")
        ax.grid(alpha=0.3)
    axes[0, 0].legend(loc="upper right", ncol=len(methods), fontsize=8)
    axes[-1, 0].set_xlabel("time [s]")
    axes[0, 0].set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)

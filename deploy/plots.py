"""PNG figures (matplotlib, non-interactive backend)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.ticker import FuncFormatter  # noqa: E402

#: tick labels of log and symlog axes as plain numbers ("0.1", "1", "10"): easier to read than
#: powers of ten for errors of centimetres to tens of metres, and they spare matplotlib its
#: mathtext parser (a third of the time of drawing the first plot of a process)
_PLAIN = FuncFormatter(lambda v, _pos: f"{v:g}")


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
    ax.yaxis.set_major_formatter(_PLAIN)
    m = res.metrics
    ax.set_title(f"SP replay: outage RMS {m['outage_h_rms_m']:.2f} m, end mean {m['outage_h_end_mean_m']:.2f} m, "
                 f"max {m['outage_h_max_m']:.2f} m (shaded: GNSS withheld)")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


#: half the width of the map's view around the scenario's origin [m]
VIEW_M = 120.0


def sigma_ellipse(cov_ne, k: float = 2.0, n: int = 48):
    """Points (east, north), shape (n, 2), of the k-σ ellipse of a north/east covariance (2, 2),
    centred on the origin."""
    import numpy as np

    w, v = np.linalg.eigh(np.asarray(cov_ne, float))
    a = np.linspace(0.0, 2.0 * np.pi, n)
    pts = (v @ (np.sqrt(np.maximum(w, 0.0))[:, None] * np.vstack([np.cos(a), np.sin(a)]))).T * k
    return pts[:, ::-1]  # (north, east) -> (east, north)


def plot_scenario(truth, path: Path, events: dict[str, float] | None = None, estimates: dict | None = None,
                  method: str | None = None, ellipse_every: float = 5.0) -> None:
    """Map of a scenario: lanes, lane lines, stop lines, true trajectories coloured by vehicle
    with their start (○, labelled), direction of travel (arrows), first stop (■) and first-stopped
    instant (★). With ``estimates`` ({vehicle: (t [s], north/east [m] (n, 2), covariance (n, 2, 2))}
    of one ``method``) the estimated tracks are drawn dashed beside the truth, with their 2σ
    ellipses every ``ellipse_every`` seconds."""
    import numpy as np

    from slcp.geo import earth
    from slcp.geo.site import offset_polyline

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
        # later vehicles of a shared lane are drawn under earlier ones, a little wider
        ax.plot(ne[:, 1], ne[:, 0], color=col, lw=1.5 + 1.2 * (len(truth.vehicles) - i - 1) / len(truth.vehicles),
                label=f"{vid} truth", zorder=4 + 0.01 * i, alpha=0.9)
        ax.plot(ne[0, 1], ne[0, 0], "o", mfc="white", mec=col, mew=1.5, ms=6, zorder=5)
        # named where it starts, or where it enters the map's view
        inside = np.flatnonzero(np.all(np.abs(ne) <= 0.95 * VIEW_M, axis=1))
        if inside.size:
            j = int(inside[0])
            ax.annotate(vid, (ne[j, 1], ne[j, 0]), textcoords="offset points", xytext=(6, 4 + 9 * (i % 2)),
                        fontsize=8, color=col, weight="bold")
        seg = np.hypot(*np.diff(ne, axis=0).T)
        s_along = np.concatenate([[0.0], np.cumsum(seg)])
        for s_mark in np.arange(30.0, s_along[-1], 60.0):  # direction of travel
            j = min(int(np.searchsorted(s_along, s_mark)), len(ne) - 2)
            if seg[j] > 1e-3:
                ax.annotate("", xy=(ne[j + 1, 1], ne[j + 1, 0]), xytext=(ne[j, 1], ne[j, 0]), zorder=5,
                            arrowprops={"arrowstyle": "-|>", "color": col, "lw": 1.2, "mutation_scale": 12})
        if estimates and vid in estimates:
            t_est, ne_est, cov_est = estimates[vid]
            if len(t_est):
                ax.plot(ne_est[:, 1], ne_est[:, 0], color=col, lw=0.8, ls="--", zorder=4.5,
                        label=f"{vid} {method or 'estimate'}")
                for j in np.flatnonzero(np.diff(np.floor(np.asarray(t_est) / ellipse_every), prepend=-1.0) > 0):
                    el = sigma_ellipse(cov_est[j]) + ne_est[j, ::-1]
                    ax.plot(el[:, 0], el[:, 1], color=col, lw=0.6, alpha=0.8, zorder=4.6)
        fs = np.flatnonzero(vt.first_stopped[::20])
        st = np.flatnonzero(vt.stopped[::20])
        if st.size:
            ax.plot(ne[st[0], 1], ne[st[0], 0], "s", color=col, mec="k", ms=7, zorder=6)
        if fs.size:
            ax.plot(ne[fs[0], 1], ne[fs[0], 0], "*", color=col, mec="k", ms=13, zorder=7)
    ax.set_aspect("equal")
    ax.set_xlabel("east [m]")
    ax.set_ylabel("north [m]")
    ax.set_xlim(-VIEW_M, VIEW_M)
    ax.set_ylim(-VIEW_M, VIEW_M)
    title = f"{scn.name}: ○ start, ■ stopped, ★ first stopped"
    if estimates:
        title += f"; dashed: {method or 'estimate'} with 2σ ellipses every {ellipse_every:g} s"
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
        for i, (_w, (a, b)) in enumerate(windows.items()):
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
        ax.yaxis.set_major_formatter(_PLAIN)
        ax.grid(alpha=0.3)
    shade = "shaded: " + ", ".join(windows) if windows else ""
    key = "solid: error, dotted: reported σ, dashed: bound" if bound is not None else "solid: error"
    axes[0, 0].legend(loc="upper right", ncol=len(methods), fontsize=8,
                      title=key + (f"; {shade}" if shade else ""), title_fontsize=7)
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
        ax.yaxis.set_major_formatter(_PLAIN)
        ax.grid(alpha=0.3)
    axes[0, 0].legend(loc="upper right", ncol=len(methods), fontsize=8)
    axes[-1, 0].set_xlabel("time [s]")
    axes[0, 0].set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)

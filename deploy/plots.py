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

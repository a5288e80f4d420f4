"""Figures of single trials (matplotlib, headless)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from flyknot.record import TrialRecord


def plot_trial(record: TrialRecord, path: str | Path) -> Path:
    """Commanded vs measured joints, marker heights, and the rope at first contact."""
    path = Path(path)
    fig = plt.figure(figsize=(13, 4.2), constrained_layout=True)
    ax1 = fig.add_subplot(1, 3, 1)
    for j in range(7):
        (line,) = ax1.plot(record.t_joint, record.q_cmd[:, j], lw=1, label=f"q{j + 1}")
        ax1.plot(record.t_joint, record.q_meas[:, j], lw=1, ls="--", color=line.get_color())
    ax1.set(
        xlabel="t [s] (robot clock)",
        ylabel="joint [rad]",
        title="command (solid), measured (dashed)",
    )
    ax1.legend(fontsize=7, ncol=4)
    ax2 = fig.add_subplot(1, 3, 2)
    for i in range(record.markers.shape[1]):
        ax2.plot(record.t_marker, record.markers[:, i, 2], lw=0.8, color=plt.cm.viridis(i / 10))
    if record.first_contact_time is not None:
        ax2.axvline(record.first_contact_time, color="k", ls=":", label="first self-contact")
        ax2.legend(fontsize=8)
    ax2.set(xlabel="t [s] (mocap clock)", ylabel="marker z [m]", title="rope markers (NaN = lost)")
    ax3 = fig.add_subplot(1, 3, 3, projection="3d")
    ok = np.all(np.isfinite(record.markers), axis=(1, 2))
    idx = np.flatnonzero(ok)
    for k in idx[:: max(1, len(idx) // 12)]:
        m = record.markers[k]
        ax3.plot(m[:, 0], m[:, 1], m[:, 2], color=plt.cm.plasma(k / max(1, idx[-1])), lw=1)
    ax3.plot(*record.fingertip_pos.T, color="k", lw=1.5, label="fingertip")
    ax3.set(xlabel="x [m]", ylabel="y [m]", zlabel="z [m]", title=f"knot: {record.knot}")
    ax3.legend(fontsize=8)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path

"""Recorded lab demonstrations in C3D or CSV, read into and written from a Demonstration.

Everything here is in the motion-capture frame, z up. A loaded demonstration is a
:class:`flyknot.demo.Demonstration` (seconds, metres, quaternions w, x, y, z; NaN where a
rope marker is lost).

CSV layout (``flyknot-demo-csv`` version 1)
-------------------------------------------
Plain text, comma separated, in SI units (s, m)::

    # flyknot-demo-csv: 1
    # t_c: 1.234
    # rope: 1
    # metadata: {"variant": "fast"}
    t,hand_x,hand_y,hand_z,hand_qw,hand_qx,hand_qy,hand_qz,m0_x,m0_y,m0_z,...,m10_x,m10_y,m10_z
    0.000,0.1,0.2,1.5,1,0,0,0,0.1,0.2,1.4,...

* Leading lines starting with ``#`` hold ``key: value`` pairs; all are optional. ``t_c``
  is the critical time [s] (the rope's first self-contact), ``rope`` the rope id, and
  ``metadata`` one line of JSON. Unknown keys are ignored.
* Then one header line naming the columns: ``t`` [s], the hand (fingertip) position
  ``hand_x..hand_z`` [m], its orientation ``hand_qw..hand_qz`` (normalised on load) and rope
  marker j's position ``mj_x, mj_y, mj_z`` [m] for j = 0 .. 10 (marker 0 is 0.10 m from the
  fingertip, marker 10 at the free end). Columns may come in any order; other columns (a
  frame number, say) are ignored.
* One row per sample, times strictly increasing. An empty marker cell or ``nan`` means the
  marker was lost; hand cells must hold numbers.

C3D conventions
---------------
* Point labels: rope markers ``rope0`` .. ``rope10`` and four markers ``hand1`` .. ``hand4``
  on a rigid cluster on the hand (other labels are ignored). A subject prefix such as
  ``Demonstrator:rope3`` (Vicon Nexus) is dropped before matching.
* Units from ``POINT:UNITS`` (``mm``, ``cm`` or ``m``; files from Vicon are in mm), converted
  to metres. Points the file marks invalid (NaN in ezc3d, or a negative residual) are lost.
* Time: frame 1 of the file is t = 0 and frame i is t = (i - 1) / ``POINT:RATE`` [s], the
  clock ``EVENT:TIMES`` uses (C3D format documentation, c3d.org, "EVENT:TIMES").
* t_c: the ``t_c`` argument, else the earliest event labelled ``critical`` or ``contact``
  (any case), time = 60 * minutes + seconds.
* Hand pose: the four hand markers sit at known points ``hand_cluster`` (4, 3) [m] of the
  hand frame, whose origin is the fingertip (default :data:`DEFAULT_HAND_CLUSTER`; pass the
  lab's measured layout). Each frame's pose (R, p) is the least-squares rigid fit of the
  layout to the visible markers (at least 3, not collinear)::

      min_{R in SO(3), p} sum_j |R c_j + p - m_j|^2,

  solved by the SVD of the cross-covariance (Kabsch's method with the reflection guard).
  The hand position is p, the orientation R as a quaternion whose sign is kept continuous
  in time. A frame with fewer than 3 visible hand markers, or a fit whose RMS residual
  exceeds ``max_fit_rms``, is an error.
* :func:`save_demo_c3d` writes mm, the hand markers from the pose and ``hand_cluster``, an
  event ``critical`` at t_c and a parameter group ``FLYKNOT`` with ``ROPE`` and
  ``METADATA`` (base64 of the JSON, split into strings of at most 200 characters).
"""

from __future__ import annotations

import base64
import csv
import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from flyknot.constants import N_MARKERS
from flyknot.demo import Demonstration
from flyknot.errors import RecordError
from flyknot.geometry import quat_sign_continuous

CSV_FORMAT_VERSION = 1
HAND_COLUMNS = (
    "hand_x",
    "hand_y",
    "hand_z",
    "hand_qw",
    "hand_qx",
    "hand_qy",
    "hand_qz",
)
MARKER_COLUMNS = tuple(f"m{j}_{a}" for j in range(N_MARKERS) for a in "xyz")
CSV_COLUMNS = ("t", *HAND_COLUMNS, *MARKER_COLUMNS)

ROPE_LABELS = tuple(f"rope{j}" for j in range(N_MARKERS))
HAND_LABELS = ("hand1", "hand2", "hand3", "hand4")
CONTACT_EVENT_LABELS = ("critical", "contact")
C3D_UNITS = {"mm": 1e-3, "cm": 1e-2, "m": 1.0}

# Hand-frame positions of hand1..hand4 [m]: an asymmetric cluster on the back of the hand,
# 6-10 cm behind the fingertip (the frame origin). Replace it with the lab's measured layout.
DEFAULT_HAND_CLUSTER = np.array(
    [
        [0.03, 0.00, 0.06],
        [-0.03, 0.00, 0.06],
        [0.00, 0.04, 0.08],
        [0.01, -0.02, 0.10],
    ]
)
DEFAULT_HAND_CLUSTER.setflags(write=False)
MAX_FIT_RMS = 0.005  # [m] RMS residual above which the hand cluster is judged mislabelled

_META_CHUNK = 200  # characters per C3D string (the format caps one string at 255 bytes)


# --- hand pose from markers ---------------------------------------------------------------


def fit_rigid(cluster: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares rigid fit of a marker layout to measured markers, frame by frame.

    min_{R, p} sum_j w_j |R c_j + p - m_j|^2 with w_j = 1 for visible markers, 0 for NaN:
    c~ = sum w c / sum w, m~ likewise, H = sum_j w_j (c_j - c~)(m_j - m~)^T = U S V^T,
    R = V diag(1, 1, det(V U^T)) U^T, p = m~ - R c~.

    Args:
        cluster: Layout c_j in the body frame, shape (n, 3) [m], n >= 3.
        points: Measured m_j, shape (k, n, 3) [m]; NaN rows are markers not seen.

    Returns:
        ``(R, p, rms)``: rotations (k, 3, 3), positions (k, 3) [m] and the RMS residual
        per frame (k,) [m]. Frames with fewer than 3 visible markers, or visible markers
        on a line, get NaN everywhere.
    """
    c = np.asarray(cluster, dtype=float)
    m = np.asarray(points, dtype=float)
    w = np.all(np.isfinite(m), axis=2).astype(float)  # (k, n)
    n_vis = w.sum(axis=1)
    m0 = np.where(w[..., None] > 0, m, 0.0)
    wsum = np.maximum(n_vis, 1.0)[:, None]
    c_bar = (w @ c) / wsum  # (k, 3)
    m_bar = np.einsum("kj,kja->ka", w, m0) / wsum
    dc = c[None] - c_bar[:, None]  # (k, n, 3)
    dm = m0 - m_bar[:, None]
    H = np.einsum("kj,kja,kjb->kab", w, dc, dm)
    U, S, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.swapaxes(Vt, 1, 2) @ np.swapaxes(U, 1, 2)))
    d = np.where(d == 0, 1.0, d)
    D = np.zeros((len(d), 3, 3))
    D[:, 0, 0] = 1.0
    D[:, 1, 1] = 1.0
    D[:, 2, 2] = d
    R = np.swapaxes(Vt, 1, 2) @ D @ np.swapaxes(U, 1, 2)
    p = m_bar - np.einsum("kab,kb->ka", R, c_bar)
    res = np.einsum("kab,jb->kja", R, c) + p[:, None] - m0
    rms = np.sqrt(np.einsum("kj,kja->k", w, res**2) / wsum[:, 0])
    scale = np.maximum(S[:, 0], 1e-300)
    bad = (n_vis < 3) | (S[:, 1] <= 1e-9 * scale)
    R[bad] = np.nan
    p[bad] = np.nan
    rms[bad] = np.nan
    return R, p, rms


def hand_pose_from_markers(
    t: np.ndarray,
    hand_markers: np.ndarray,
    hand_cluster: np.ndarray = DEFAULT_HAND_CLUSTER,
    max_fit_rms: float = MAX_FIT_RMS,
) -> tuple[np.ndarray, np.ndarray]:
    """Hand pose from the cluster markers (see :func:`fit_rigid`).

    Args:
        t: Frame times, shape (k,) [s] (only for messages).
        hand_markers: Measured hand1..hand4, shape (k, 4, 3) [m], NaN where not seen.
        hand_cluster: Their positions in the hand frame, shape (4, 3) [m].
        max_fit_rms: Largest acceptable RMS residual of the fit [m].

    Returns:
        ``(hand_pos (k, 3) [m], hand_quat (k, 4) (w, x, y, z))``.

    Raises:
        RecordError: A frame without a pose, or a fit worse than ``max_fit_rms``.
    """
    cluster = np.asarray(hand_cluster, dtype=float)
    if cluster.shape != (len(HAND_LABELS), 3) or not np.all(np.isfinite(cluster)):
        raise RecordError(
            f"hand_cluster must be a finite array of shape ({len(HAND_LABELS)}, 3), "
            f"got {cluster.shape}"
        )
    R, p, rms = fit_rigid(cluster, hand_markers)
    undefined = np.isnan(rms)
    if undefined.any():
        i = int(np.argmax(undefined))
        raise RecordError(
            f"hand pose undefined in {int(undefined.sum())} frame(s), first at t = {t[i]:.4f} s: "
            f"fewer than 3 of {', '.join(HAND_LABELS)} visible, or they lie on a line"
        )
    worst = int(np.argmax(rms))
    if rms[worst] > max_fit_rms:
        raise RecordError(
            f"hand markers do not fit hand_cluster: RMS residual {rms[worst]:.4g} m at "
            f"t = {t[worst]:.4f} s exceeds max_fit_rms = {max_fit_rms} m (pass the lab's "
            "hand_cluster layout)"
        )
    q = Rotation.from_matrix(R).as_quat(scalar_first=True)
    return p, quat_sign_continuous(q, first_positive=True)


def hand_markers_from_pose(
    hand_pos: np.ndarray, hand_quat: np.ndarray, hand_cluster: np.ndarray = DEFAULT_HAND_CLUSTER
) -> np.ndarray:
    """Where the hand markers are for a hand pose: m_j = R(q) c_j + p.

    Args:
        hand_pos: p, shape (k, 3) [m].
        hand_quat: q (w, x, y, z), shape (k, 4).
        hand_cluster: c_j, shape (4, 3) [m].

    Returns:
        Markers, shape (k, 4, 3) [m].
    """
    R = Rotation.from_quat(np.asarray(hand_quat, dtype=float), scalar_first=True).as_matrix()
    return (
        np.einsum("kab,jb->kja", R, np.asarray(hand_cluster, dtype=float))
        + np.asarray(hand_pos, dtype=float)[:, None]
    )


# --- CSV ----------------------------------------------------------------------------------


def _fmt(x: float) -> str:
    return "" if math.isnan(x) else repr(float(x))


def save_demo_csv(demo: Demonstration, path: str | Path) -> None:
    """Write ``demo`` in the CSV layout of the module docstring (full float precision)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    data = np.column_stack(
        [demo.t, demo.hand_pos, demo.hand_quat, demo.markers.reshape(len(demo.t), -1)]
    )
    lines = [
        f"# flyknot-demo-csv: {CSV_FORMAT_VERSION}",
        f"# t_c: {demo.t_c!r}",
        f"# rope: {demo.rope}",
        f"# metadata: {json.dumps(dict(demo.metadata), sort_keys=True)}",
        ",".join(CSV_COLUMNS),
    ]
    lines += [",".join(_fmt(x) for x in row) for row in data]
    path.write_text("\n".join(lines) + "\n")


def _parse_cell(text: str, where: str) -> float:
    s = text.strip()
    if s == "" or s.lower() == "nan":
        return math.nan
    try:
        return float(s)
    except ValueError:
        raise RecordError(f"{where}: {s!r} is not a number") from None


def load_demo_csv(
    path: str | Path,
    *,
    t_c: float | None = None,
    rope: int | None = None,
    metadata: Mapping[str, Any] | None = None,
) -> Demonstration:
    """Read a CSV demonstration (layout in the module docstring).

    Args:
        path: The file.
        t_c: Critical time [s]; overrides the file's ``# t_c:`` line.
        rope: Rope id; overrides the file's ``# rope:`` line (default 1).
        metadata: Merged over the file's ``# metadata:`` JSON.

    Returns:
        The demonstration.

    Raises:
        RecordError: Missing file, columns or t_c; unreadable cells; missing hand values.
    """
    path = Path(path)
    if not path.is_file():
        raise RecordError(f"demonstration file {str(path)!r} does not exist")
    try:
        lines = path.read_text().splitlines()
    except UnicodeDecodeError:
        raise RecordError(f"{str(path)!r} is not a text file (a CSV demonstration)") from None
    header, n = _csv_header(lines, path)
    data, line_nos = _csv_table(lines[n:], n, path)
    if t_c is None:
        if "t_c" not in header:
            raise RecordError(
                f"{str(path)!r} has no '# t_c: <seconds>' line; pass t_c= to the loader"
            )
        t_c = _parse_cell(header["t_c"], f"{str(path)!r} '# t_c' line")
    if rope is None:
        rope = int(_parse_cell(header.get("rope", "1"), f"{str(path)!r} '# rope' line"))
    meta: dict[str, Any] = {}
    if "metadata" in header:
        try:
            meta = dict(json.loads(header["metadata"]))
        except (ValueError, TypeError) as e:
            raise RecordError(f"{str(path)!r} '# metadata' line is not a JSON object: {e}") from e
    meta.update(metadata or {})
    quat = data[:, 4:8]
    norm = np.linalg.norm(quat, axis=1)
    if np.any(norm < 1e-9):
        i = int(np.argmax(norm < 1e-9))
        raise RecordError(f"{str(path)!r} line {line_nos[i]}: hand quaternion is zero")
    return Demonstration(
        t=data[:, 0],
        hand_pos=data[:, 1:4],
        hand_quat=quat / norm[:, None],
        markers=data[:, 8:].reshape(-1, N_MARKERS, 3),
        t_c=t_c,
        rope=rope,
        metadata=meta,
    )


def _csv_header(lines: list[str], path: Path) -> tuple[dict[str, str], int]:
    """The ``# key: value`` lines before the column names (keys lower-cased) and the index
    of the column names' line; the format version checked."""
    header: dict[str, str] = {}
    n = 0
    while n < len(lines) and (lines[n].startswith("#") or not lines[n].strip()):
        key, sep, value = lines[n][1:].partition(":")
        if sep:
            header[key.strip().lower()] = value.strip()
        n += 1
    if n == len(lines):
        raise RecordError(f"{str(path)!r} has no header line")
    version = header.get("flyknot-demo-csv", str(CSV_FORMAT_VERSION))
    if version != str(CSV_FORMAT_VERSION):
        raise RecordError(
            f"{str(path)!r}: flyknot-demo-csv version {version!r} is not supported "
            f"(valid choices: {CSV_FORMAT_VERSION})"
        )
    return header, n


def _csv_table(lines: list[str], n: int, path: Path) -> tuple[np.ndarray, list[int]]:
    """The table from its column names' line on (file line ``n + 1``): the values of
    :data:`CSV_COLUMNS` per non-blank row, (k, 41), k >= 2, time and hand values finite; and
    each row's file line number."""
    rows = list(csv.reader(lines))
    names = [h.strip() for h in rows[0]]
    missing = [c for c in CSV_COLUMNS if c not in names]
    if missing:
        raise RecordError(f"{str(path)!r} lacks columns: {', '.join(missing)}")
    dup = sorted({c for c in CSV_COLUMNS if names.count(c) > 1})
    if dup:
        raise RecordError(f"{str(path)!r} repeats columns: {', '.join(dup)}")
    col = [names.index(c) for c in CSV_COLUMNS]
    body = [(n + 2 + i, r) for i, r in enumerate(rows[1:]) if any(x.strip() for x in r)]
    data = np.empty((len(body), len(CSV_COLUMNS)))
    for i, (line_no, r) in enumerate(body):
        if len(r) != len(names):
            raise RecordError(
                f"{str(path)!r} line {line_no}: expected {len(names)} values, got {len(r)}"
            )
        for j, c in enumerate(col):
            data[i, j] = _parse_cell(r[c], f"{str(path)!r} line {line_no}, column {names[c]}")
    if len(body) < 2:
        raise RecordError(f"{str(path)!r} needs at least 2 samples, got {len(body)}")
    bad = ~np.isfinite(data[:, : 1 + len(HAND_COLUMNS)])
    if bad.any():
        i, j = np.argwhere(bad)[0]
        raise RecordError(
            f"{str(path)!r} line {body[i][0]}: column {CSV_COLUMNS[j]} must hold a number "
            f"({int(bad.any(axis=1).sum())} row(s) lack time or hand values)"
        )
    return data, [line_no for line_no, _ in body]


# --- C3D ----------------------------------------------------------------------------------


def _import_ezc3d():
    try:
        import ezc3d
    except ImportError as e:  # pragma: no cover - ezc3d is a dependency
        raise RecordError("reading or writing C3D needs the ezc3d package") from e
    return ezc3d


def _strip_subject(label: str) -> str:
    return label.strip().rsplit(":", 1)[-1].strip()


def _param(c3d: Any, group: str, name: str) -> Any | None:
    params = c3d["parameters"]
    if group in params and name in params[group]:
        return params[group][name]["value"]
    return None


def load_demo_c3d(
    path: str | Path,
    *,
    t_c: float | None = None,
    rope: int | None = None,
    hand_cluster: np.ndarray = DEFAULT_HAND_CLUSTER,
    max_fit_rms: float = MAX_FIT_RMS,
    rope_labels: Sequence[str] = ROPE_LABELS,
    hand_labels: Sequence[str] = HAND_LABELS,
    metadata: Mapping[str, Any] | None = None,
) -> Demonstration:
    """Read a C3D demonstration (conventions in the module docstring).

    Args:
        path: The file.
        t_c: Critical time [s] on the file's clock; None = from a ``critical``/``contact``
            event.
        rope: Rope id; None = ``FLYKNOT:ROPE`` if present, else 1.
        hand_cluster: Hand-frame positions of the four hand markers, shape (4, 3) [m].
        max_fit_rms: Largest acceptable RMS residual of the hand fit [m].
        rope_labels: The 11 rope marker labels, fingertip end first.
        hand_labels: The 4 hand marker labels, in ``hand_cluster``'s order.
        metadata: Merged over ``FLYKNOT:METADATA``.

    Returns:
        The demonstration.

    Raises:
        RecordError: Missing file, labels, event or units; undefined hand pose.
    """
    ezc3d = _import_ezc3d()
    path = Path(path)
    if not path.is_file():
        raise RecordError(f"demonstration file {str(path)!r} does not exist")
    if len(rope_labels) != N_MARKERS or len(hand_labels) != len(HAND_LABELS):
        raise RecordError(
            f"rope_labels needs {N_MARKERS} labels and hand_labels {len(HAND_LABELS)}, got "
            f"{len(rope_labels)} and {len(hand_labels)}"
        )
    try:
        c3d = ezc3d.c3d(str(path))
    except (RuntimeError, OSError, ValueError) as e:  # what ezc3d raises on bad files
        raise RecordError(f"{str(path)!r} is not a readable C3D file: {e}") from e

    want = [*rope_labels, *hand_labels]
    idx = _c3d_label_index(c3d, want, path)
    t, xyz = _c3d_points(c3d, path)
    markers = xyz[:, idx[:N_MARKERS]]
    hand_pos, hand_quat = hand_pose_from_markers(
        t, xyz[:, idx[N_MARKERS:]], hand_cluster, max_fit_rms
    )

    if t_c is None:
        t_c = _contact_event(c3d, path)
        # C3D stores times as float32: snap an event within 1e-6 s of the ends inside.
        if t[0] - 1e-6 <= t_c <= t[-1] + 1e-6:
            t_c = min(max(t_c, float(t[0])), float(t[-1]))
    if rope is None:
        r = _param(c3d, "FLYKNOT", "ROPE")
        rope = int(np.ravel(r)[0]) if r is not None and np.size(r) else 1
    meta: dict[str, Any] = {}
    chunks = _param(c3d, "FLYKNOT", "METADATA")
    if chunks:
        try:
            meta = dict(json.loads(base64.b64decode("".join(c.strip() for c in chunks))))
        except (ValueError, TypeError) as e:
            raise RecordError(f"{str(path)!r}: FLYKNOT:METADATA is unreadable: {e}") from e
    meta.update(metadata or {})
    return Demonstration(
        t=t,
        hand_pos=hand_pos,
        hand_quat=hand_quat,
        markers=markers,
        t_c=t_c,
        rope=rope,
        metadata=meta,
    )


def _c3d_label_index(c3d: Any, want: list[str], path: Path) -> list[int]:
    """The POINT columns of the ``want`` labels (subject prefixes stripped), each present
    once."""
    labels = [_strip_subject(s) for s in (_param(c3d, "POINT", "LABELS") or [])]
    missing = [s for s in want if s not in labels]
    if missing:
        raise RecordError(
            f"{str(path)!r} lacks marker labels: {', '.join(missing)} "
            f"(found: {', '.join(labels) if labels else 'none'})"
        )
    dup = [s for s in want if labels.count(s) > 1]
    if dup:
        raise RecordError(f"{str(path)!r} repeats marker labels: {', '.join(sorted(set(dup)))}")
    return [labels.index(s) for s in want]


def _c3d_points(c3d: Any, path: Path) -> tuple[np.ndarray, np.ndarray]:
    """The frames' times (k,) [s] and every label's point (k, n_labels, 3) [m], NaN where
    the file marks it invalid (a negative residual)."""
    units = (_param(c3d, "POINT", "UNITS") or ["mm"])[0].strip().lower() or "mm"
    if units not in C3D_UNITS:
        raise RecordError(
            f"{str(path)!r}: POINT:UNITS {units!r} is not supported "
            f"(valid choices: {', '.join(C3D_UNITS)})"
        )
    rate = float(np.ravel(_param(c3d, "POINT", "RATE"))[0])
    if not rate > 0:
        raise RecordError(f"{str(path)!r}: POINT:RATE must be > 0, got {rate}")
    pts = np.asarray(c3d["data"]["points"], dtype=float)  # (4, n_labels, k)
    xyz = pts[:3].transpose(2, 1, 0) * C3D_UNITS[units]  # (k, n_labels, 3) [m]
    residuals = c3d["data"]["meta_points"]["residuals"]  # (1, n_labels, k)
    xyz[np.asarray(residuals)[0].T < 0] = np.nan
    first = int(c3d["header"]["points"]["first_frame"])  # 0-based in ezc3d
    return (first + np.arange(xyz.shape[0])) / rate, xyz


def _contact_event(c3d: Any, path: Path) -> float:
    """Earliest event labelled critical/contact: t = 60 * minutes + seconds [s]."""
    labels = [str(s).strip() for s in (_param(c3d, "EVENT", "LABELS") or [])]
    times = _param(c3d, "EVENT", "TIMES")
    found = []
    if labels and times is not None:
        times = np.asarray(times, dtype=float).reshape(2, -1)
        for i, s in enumerate(labels):
            if s.lower() in CONTACT_EVENT_LABELS and i < times.shape[1]:
                found.append(60.0 * times[0, i] + times[1, i])
    if not found:
        raise RecordError(
            f"{str(path)!r} has no event labelled {' or '.join(CONTACT_EVENT_LABELS)} "
            f"(events: {', '.join(labels) if labels else 'none'}); pass t_c= to the loader"
        )
    return float(min(found))


def save_demo_c3d(
    demo: Demonstration, path: str | Path, hand_cluster: np.ndarray = DEFAULT_HAND_CLUSTER
) -> None:
    """Write ``demo`` as C3D (mm, rope and hand markers, a ``critical`` event, FLYKNOT group).

    The samples must be uniform and start on the frame grid: t_i = (f + i) / rate with an
    integer f >= 0 (within 1e-6 s), since C3D stores a rate and a first frame, not times.

    Raises:
        RecordError: Non-uniform samples, a start off the frame grid or oversized metadata.
    """
    ezc3d = _import_ezc3d()
    path = Path(path)
    t = demo.t
    rate = demo.rate_hz
    first = round(float(t[0] * rate))
    grid = (first + np.arange(len(t))) / rate
    err = float(np.max(np.abs(grid - t)))
    if first < 0 or err > 1e-6:
        raise RecordError(
            f"C3D needs uniform samples starting on the frame grid at {rate:.6g} Hz; the "
            f"demonstration's times are off it by up to {err:.3g} s (t[0] = {t[0]} s)"
        )
    cluster = np.asarray(hand_cluster, dtype=float)
    hand = hand_markers_from_pose(demo.hand_pos, demo.hand_quat, cluster)
    xyz = np.concatenate([demo.markers, hand], axis=1) * 1e3  # (k, 15, 3) [mm]
    pts = np.ones((4, xyz.shape[1], len(t)))
    pts[:3] = xyz.transpose(2, 1, 0)

    c3d = ezc3d.c3d()
    c3d["parameters"]["POINT"]["RATE"]["value"] = [rate]
    c3d["parameters"]["POINT"]["UNITS"]["value"] = ["mm"]
    c3d["parameters"]["POINT"]["LABELS"]["value"] = [*ROPE_LABELS, *HAND_LABELS]
    c3d["data"]["points"] = pts
    # C3D marks a missing point by a negative residual (C3D format documentation, c3d.org).
    lost = ~np.all(np.isfinite(xyz), axis=2).T  # (15, k)
    c3d["data"]["meta_points"] = {
        "residuals": np.where(lost, -1.0, 0.0)[None],
        "camera_masks": np.zeros((7, *lost.shape), dtype=bool),
    }
    c3d["header"]["points"]["first_frame"] = first
    minutes = math.floor(demo.t_c / 60.0)
    c3d.add_event([minutes, demo.t_c - 60.0 * minutes], context="General", label="critical")
    c3d.add_parameter("FLYKNOT", "ROPE", [demo.rope])
    blob = base64.b64encode(json.dumps(dict(demo.metadata), sort_keys=True).encode()).decode()
    chunks = [blob[i : i + _META_CHUNK] for i in range(0, len(blob), _META_CHUNK)] or [""]
    if len(chunks) > 255:
        raise RecordError(
            f"demonstration metadata is too large for C3D ({len(blob)} base64 characters, "
            f"at most {255 * _META_CHUNK})"
        )
    c3d.add_parameter("FLYKNOT", "METADATA", chunks)
    path.parent.mkdir(parents=True, exist_ok=True)
    c3d.write(str(path))


def read_demonstration(path: str | Path) -> Demonstration:
    """A demonstration read by its file's suffix: ``.npz`` (:meth:`Demonstration.load`),
    ``.csv`` (:func:`load_demo_csv`) or ``.c3d`` (:func:`load_demo_c3d`).

    Raises:
        RecordError: Another suffix, or a file its reader cannot read (naming it).
    """
    path = Path(path)
    readers = {".npz": Demonstration.load, ".csv": load_demo_csv, ".c3d": load_demo_c3d}
    suffix = path.suffix.lower()
    if suffix not in readers:
        raise RecordError(
            f"{str(path)!r}: a demonstration is a .npz, .csv or .c3d file, not {suffix or 'none'!r}"
        )
    return readers[suffix](path)

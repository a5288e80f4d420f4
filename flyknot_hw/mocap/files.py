"""Recordings written by the lab's own capture software: C3D and a simple CSV, matched to trials.

**C3D** (:func:`read_c3d`, :func:`write_c3d`; needs the pure-Python ``c3d`` package of the
``mocap`` extra). Frame ``n`` (C3D counts from 1) is at ``t = (n - 1) / rate`` on the mocap
clock, so a trimmed file keeps its place on the capture's clock. Points whose residual is
negative are missing (NaN). Units from ``POINT:UNITS`` ("mm" or "m"). Labels are discarded
for the rope: every point not claimed by a body becomes an unlabelled point (a swap in the
capture software's labels cannot reach the rope labelling). ``body_labels`` names clusters:
``{"fingertip": ["tip1", "tip2", "tip3"]}`` makes a body whose position is the mean of those
points (NaN in a frame where any is missing; no orientation). ``clusters`` finds them by name:
``("fingertip",)`` makes the body ``fingertip`` of every point labelled ``fingertip`` followed
by a number (``fingertip1``, ``fingertip_2``, ``Hand:fingertip3``; :func:`cluster_labels`), and
no body when the file has none.

**CSV** (:func:`read_csv`, :func:`write_csv`), the layout to export from any other software::

    # comment lines start with '#'
    t,p0.x,p0.y,p0.z,p1.x,p1.y,p1.z,fingertip.x,fingertip.y,fingertip.z,fingertip.qw,...
    0.000,0.4012,0.0031,1.1943,,,,0.4000,0.0000,1.2998,1.0,...

``t`` is the frame time [s] on the mocap clock (increasing); every other column is
``<label>.<axis>`` with axes x, y, z (positions, in ``units``: metres by default) and
optionally qw, qx, qy, qz (orientation). A label with orientation columns, or named in
``body_names``, is a body; every other label is an unlabelled point. An empty field or
``nan`` is a missing value.

**Matching a recording to a trial** (:func:`match_recording`), in this order:

Only file names matching ``pattern`` (a glob such as ``trial_*.c3d``) take part, and never
a file listed in ``exclude`` (``name -> (size, mtime_ns)`` as it was before the trial, so
that a file already there and unchanged is not taken for the trial's):

1. By name: with ``trial_stem`` (e.g. ``trial_0007``), the file whose stem equals it, else
   the single file whose name contains it (the operator names the capture after the trial,
   or the lab software is told the name). Several candidates: an error listing them.
2. By time: with ``trial_start`` and ``trial_end`` (host wall clock, seconds since the
   epoch). A file whose name holds a time stamp (``YYYYMMDD?HHMMSS`` with optional
   ``-``/``_``/``T`` separators, local time: the capture's start) matches if the stamp lies
   in ``[trial_start - lead_s, trial_start + slack_s]``; of several, the latest (the capture
   started last before the trial). Without stamped matches, a file matches if its
   modification time (the end of writing) lies in ``[trial_end - slack_s, trial_end + lag_s]``;
   of several, the earliest (the first capture to end after the trial). None: an error.
   The host and capture computers' wall clocks must agree to within ``slack_s``.
"""

from __future__ import annotations

import csv
import fnmatch
import math
import re
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from datetime import datetime
from pathlib import Path

import numpy as np

from flyknot.errors import ConfigError, HardwareError, RecordError, check_choice, check_positive
from flyknot_hw.mocap.stream import BodyTrack, RawStream

__all__ = [
    "RECORDING_SUFFIXES",
    "RecordedFileSource",
    "cluster_labels",
    "match_recording",
    "read_c3d",
    "read_csv",
    "read_recording",
    "write_c3d",
    "write_csv",
]

RECORDING_SUFFIXES = (".c3d", ".csv")
_UNITS = {"m": 1.0, "mm": 1e-3}
_STAMP = re.compile(r"(\d{4})-?(\d{2})-?(\d{2})[T_\- ]?(\d{2})[-:]?(\d{2})[-:]?(\d{2})")


def _c3d():
    try:
        import c3d  # optional dependency (the mocap extra), imported when used
    except ImportError as e:
        raise HardwareError(
            "reading C3D files needs the 'c3d' package: pip install 'flyknot[mocap]'"
        ) from e
    return c3d


def _pad(frames: list[np.ndarray]) -> np.ndarray:
    """Frames of (P_f, 3) points -> (m, max P_f, 3), NaN padded."""
    width = max((f.shape[0] for f in frames), default=0)
    out = np.full((len(frames), width, 3), np.nan)
    for k, f in enumerate(frames):
        out[k, : f.shape[0]] = f
    return out


def _body_columns(labels: list[str], body_labels: Mapping[str, Sequence[str]]) -> dict:
    cols = {}
    for name, parts in body_labels.items():
        missing = [p for p in parts if p not in labels]
        if not parts or missing:
            raise ConfigError(
                f"body_labels[{name!r}]", f"labels {missing or list(parts)} not in file", labels
            )
        cols[name] = [labels.index(p) for p in parts]
    return cols


def cluster_labels(labels: Sequence[str], name: str) -> list[str]:
    """The labels of the marker cluster ``name``: ``name`` followed by a number, optionally
    after a subject prefix (``Hand:``) and a separator (``fingertip1``, ``fingertip_2``,
    ``Hand:fingertip3``), case-insensitive; in the order given."""
    rx = re.compile(rf"^(?:[^:]*:)?{re.escape(name)}[ _.\-]?\d+$", re.IGNORECASE)
    return [str(x) for x in labels if rx.match(str(x).strip())]


def _with_clusters(
    labels: list[str], body_labels: Mapping[str, Sequence[str]] | None, clusters: Sequence[str]
) -> dict[str, Sequence[str]]:
    out = dict(body_labels or {})
    for name in clusters:
        found = cluster_labels(labels, name)
        if found and name not in out:
            out[name] = found
    return out


def read_c3d(
    path: str | Path,
    *,
    body_labels: Mapping[str, Sequence[str]] | None = None,
    clusters: Sequence[str] = (),
) -> RawStream:
    """Read a C3D recording into a :class:`RawStream` (conventions: module docstring).

    Args:
        path: The ``.c3d`` file.
        body_labels: Body name -> point labels whose mean is the body's position.
        clusters: Names of marker clusters to make bodies of, when the file has them
            (:func:`cluster_labels`).

    Raises:
        RecordError: The file is missing or not a readable C3D.
        ConfigError: A body label is not in the file (the error lists the labels).
    """
    path = Path(path)
    if not path.is_file():
        raise RecordError(f"C3D file {str(path)!r} does not exist")
    c3d = _c3d()
    with path.open("rb") as fh, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            reader = c3d.Reader(fh)
            rate = float(reader.point_rate)
            labels = [str(s).strip() for s in reader.point_labels]
            units = reader.get("POINT:UNITS")
            unit = units.string_value.strip().lower() if units is not None else "mm"
            frames = list(reader.read_frames(copy=True))
        except Exception as e:  # the reader raises assorted errors on a broken file
            raise RecordError(f"{str(path)!r} is not a readable C3D file: {e}") from e
    check_choice(f"{path.name} POINT:UNITS", unit, list(_UNITS))
    if not frames:
        raise RecordError(f"C3D file {str(path)!r} holds no frames")
    scale = _UNITS[unit]
    numbers = np.array([f[0] for f in frames], dtype=float)
    xyz = np.stack([f[1][:, :3] for f in frames]).astype(float) * scale
    xyz[np.stack([f[1][:, 3] for f in frames]) < 0] = np.nan
    labels += [f"_{k}" for k in range(len(labels), xyz.shape[1])]
    bodies = {}
    claimed: set[int] = set()
    labels = labels[: xyz.shape[1]]
    for name, cols in _body_columns(labels, _with_clusters(labels, body_labels, clusters)).items():
        bodies[name] = BodyTrack.positions_only(xyz[:, cols].mean(axis=1))
        claimed.update(cols)
    free = [k for k in range(xyz.shape[1]) if k not in claimed]
    frames_pts = [row[np.all(np.isfinite(row), axis=1)] for row in xyz[:, free]]
    return RawStream((numbers - 1.0) / rate, _pad(frames_pts), bodies, source=str(path))


def _uniform_frames(stream: RawStream, rate_hz: float) -> np.ndarray:
    n = stream.times * rate_hz
    k = np.round(n)
    if np.any(np.abs(n - k) > 1e-3) or np.any(k < 0):
        raise ConfigError(
            "stream.times", f"C3D needs frames on a uniform clock k / {rate_hz:g} Hz, k >= 0"
        )
    return k.astype(int)


def write_c3d(
    path: str | Path,
    stream: RawStream,
    *,
    rate_hz: float,
    labels: Sequence[str] | None = None,
    units: str = "mm",
) -> Path:
    """Write a stream as C3D: its points (labelled ``labels``, default ``p0, p1, ...``) and
    each body as one point labelled with its name. Missing frames between the stream's frames
    are written as missing points.

    Args:
        path: Output file.
        stream: Frames at times k / rate_hz (k >= 0 integers) [s].
        rate_hz: Frame rate [Hz].
        labels: Labels of the P points.
        units: "mm" (what capture software writes) or "m".
    """
    c3d = _c3d()
    check_positive("rate_hz", rate_hz)
    check_choice("units", units, list(_UNITS))
    k = _uniform_frames(stream, rate_hz)
    n_pts = stream.points.shape[1]
    names = [f"p{i}" for i in range(n_pts)] if labels is None else [str(s) for s in labels]
    if len(names) != n_pts:
        raise ConfigError("labels", f"must name the {n_pts} points, got {len(names)}")
    names += list(stream.bodies)
    xyz = np.concatenate(
        [stream.points, *[b.position[:, None, :] for b in stream.bodies.values()]], axis=1
    )
    span = k[-1] - k[0] + 1
    data = np.full((span, len(names), 3), np.nan)
    data[k - k[0]] = xyz / _UNITS[units]
    writer = c3d.Writer(point_rate=float(rate_hz), point_units=f"{units:<4}")
    frames = []
    for row in data:
        pts = np.zeros((len(names), 5), dtype=np.float32)
        ok = np.all(np.isfinite(row), axis=1)
        pts[ok, :3] = row[ok]
        pts[~ok, 3] = -1.0
        frames.append((pts, np.zeros((0, 0), dtype=np.float32)))
    writer.add_frames(frames)
    writer.set_point_labels(names)
    writer.set_start_frame(int(k[0]) + 1)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("wb") as fh, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "No analog data found": there is none to write
        writer.write(fh)
    return path


def _float(text: str) -> float:
    text = text.strip()
    return math.nan if text == "" else float(text)


def read_csv(
    path: str | Path,
    *,
    body_names: Sequence[str] = (),
    units: str = "m",
    clusters: Sequence[str] = (),
) -> RawStream:
    """Read the CSV layout of the module docstring into a :class:`RawStream`.

    ``clusters``: names of marker clusters whose points (:func:`cluster_labels`) become a
    body at their mean, when the file has them.

    Raises:
        RecordError: Missing file, bad header, unparsable or non-increasing rows.
    """
    path = Path(path)
    check_choice("units", units, list(_UNITS))
    if not path.is_file():
        raise RecordError(f"CSV file {str(path)!r} does not exist")
    lines = [ln for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    if not lines:
        raise RecordError(f"CSV file {str(path)!r} is empty")
    rows = list(csv.reader(lines))
    header = [h.strip() for h in rows[0]]
    if header[0] != "t":
        raise RecordError(f"{str(path)!r}: the first column must be 't', got {header[0]!r}")
    groups: dict[str, dict[str, int]] = {}
    for c, h in enumerate(header[1:], start=1):
        label, _, axis = h.rpartition(".")
        if not label or axis not in ("x", "y", "z", "qw", "qx", "qy", "qz"):
            raise RecordError(
                f"{str(path)!r}: column {h!r} is not <label>.<axis> (axes x, y, z, qw, qx, qy, qz)"
            )
        groups.setdefault(label, {})[axis] = c
    try:
        data = np.array([[_float(v) for v in r] for r in rows[1:]], dtype=float)
    except ValueError as e:
        raise RecordError(f"{str(path)!r}: {e}") from e
    if data.ndim != 2 or data.shape[0] == 0 or data.shape[1] != len(header):
        raise RecordError(f"{str(path)!r}: every row needs {len(header)} values")
    scale = _UNITS[units]
    bodies, points = {}, []
    member = {lb: name for name in clusters for lb in cluster_labels(list(groups), name)}
    parts: dict[str, list[np.ndarray]] = {}
    for label, axes in groups.items():
        if not {"x", "y", "z"} <= set(axes):
            raise RecordError(f"{str(path)!r}: label {label!r} lacks x, y or z")
        xyz = data[:, [axes["x"], axes["y"], axes["z"]]] * scale
        has_q = {"qw", "qx", "qy", "qz"} <= set(axes)
        if label in member and not has_q and label not in body_names:
            parts.setdefault(member[label], []).append(xyz)
        elif has_q or label in body_names:
            quat = data[:, [axes[a] for a in ("qw", "qx", "qy", "qz")]] if has_q else None
            bodies[label] = (
                BodyTrack(xyz, quat) if quat is not None else BodyTrack.positions_only(xyz)
            )
        else:
            points.append(xyz)
    for name, xyzs in parts.items():
        if name not in bodies:
            bodies[name] = BodyTrack.positions_only(np.mean(np.stack(xyzs), axis=0))
    missing = [b for b in body_names if b not in bodies]
    if missing:
        raise ConfigError("body_names", f"{missing} not in {path.name}", sorted(groups))
    stacked = np.stack(points, axis=1) if points else np.zeros((data.shape[0], 0, 3))
    frames = [row[np.all(np.isfinite(row), axis=1)] for row in stacked]
    try:
        return RawStream(data[:, 0], _pad(frames), bodies, source=str(path))
    except ConfigError as e:
        raise RecordError(f"{str(path)!r}: {e}") from e


def write_csv(path: str | Path, stream: RawStream, *, units: str = "m") -> Path:
    """Write a stream in the CSV layout (points ``p0..``, bodies with orientation)."""
    check_choice("units", units, list(_UNITS))
    scale = _UNITS[units]
    header, cols = ["t"], [stream.times[:, None]]
    for i in range(stream.points.shape[1]):
        header += [f"p{i}.x", f"p{i}.y", f"p{i}.z"]
        cols.append(stream.points[:, i] / scale)
    for name, body in stream.bodies.items():
        header += [f"{name}.{a}" for a in ("x", "y", "z", "qw", "qx", "qy", "qz")]
        cols += [body.position / scale, body.quat]
    data = np.hstack(cols)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    text = [",".join(header)]
    text += [",".join("" if not np.isfinite(v) else f"{v:.9g}" for v in row) for row in data]
    path.write_text("\n".join(text) + "\n")
    return path


def read_recording(path: str | Path, **kwargs) -> RawStream:
    """:func:`read_c3d` or :func:`read_csv` by the file's suffix."""
    path = Path(path)
    readers: dict[str, Callable[..., RawStream]] = {".c3d": read_c3d, ".csv": read_csv}
    check_choice("recording suffix", path.suffix.lower(), list(readers))
    return readers[path.suffix.lower()](path, **kwargs)


def name_time(name: str) -> float | None:
    """Time stamp in a file name (``YYYYMMDD?HHMMSS``, local time) as epoch seconds, or None."""
    m = _STAMP.search(name)
    if m is None:
        return None
    try:
        return datetime(*(int(g) for g in m.groups())).timestamp()
    except ValueError:
        return None


def match_recording(
    directory: str | Path,
    *,
    trial_stem: str | None = None,
    trial_start: float | None = None,
    trial_end: float | None = None,
    suffixes: Sequence[str] = RECORDING_SUFFIXES,
    pattern: str | None = None,
    exclude: Mapping[str, tuple[int, int]] | None = None,
    lead_s: float = 30.0,
    lag_s: float = 60.0,
    slack_s: float = 2.0,
) -> Path:
    """The recording of one trial in ``directory`` (rules in the module docstring).

    ``pattern``: a glob the file names must match (None: any name); ``exclude``: files to
    skip while unchanged, name -> (size [bytes], mtime_ns) (:func:`directory_snapshot`).

    Raises:
        HardwareError: No file matches, or several match ``trial_stem``.
        ConfigError: Neither ``trial_stem`` nor both trial times are given.
    """
    directory = Path(directory)
    if not directory.is_dir():
        raise HardwareError(f"recordings directory {str(directory)!r} does not exist")
    skip = dict(exclude or {})
    files = sorted(
        p
        for p in directory.iterdir()
        if p.is_file()
        and p.suffix.lower() in suffixes
        and (pattern is None or fnmatch.fnmatch(p.name, pattern))
        and skip.get(p.name) != _stat_key(p)
    )
    if trial_stem is not None:
        exact = [p for p in files if p.stem == trial_stem]
        found = exact or [p for p in files if trial_stem in p.name]
        how = f"named after {trial_stem!r}"
    elif trial_start is not None and trial_end is not None:
        stamped, written = [], []
        for p in files:
            stamp = name_time(p.name)
            if stamp is not None:
                if trial_start - lead_s <= stamp <= trial_start + slack_s:
                    stamped.append((stamp, p))
            else:
                mtime = p.stat().st_mtime
                if trial_end - slack_s <= mtime <= trial_end + lag_s:
                    written.append((mtime, p))
        pick = [max(stamped)] if stamped else [min(written)] if written else []
        found = [p for _, p in pick]
        how = "recorded at the trial's time"
    else:
        raise ConfigError("match_recording", "give trial_stem, or trial_start and trial_end")
    if len(found) != 1:
        names = ", ".join(p.name for p in found) or "none"
        kinds = f"named {pattern}" if pattern else f"suffixes {', '.join(suffixes)}"
        raise HardwareError(
            f"expected one recording {how} in {str(directory)!r} ({kinds}"
            f"{', new since the trial began' if skip else ''}), found {len(found)}: {names}"
        )
    return found[0]


def _stat_key(path: Path) -> tuple[int, int] | None:
    try:
        st = path.stat()
    except OSError:
        return None
    return st.st_size, st.st_mtime_ns


def directory_snapshot(directory: str | Path) -> dict[str, tuple[int, int]]:
    """Every file in ``directory`` as name -> (size [bytes], mtime_ns), for ``exclude``."""
    directory = Path(directory)
    if not directory.is_dir():
        return {}
    out = {}
    for p in directory.iterdir():
        key = _stat_key(p) if p.is_file() else None
        if key is not None:
            out[p.name] = key
    return out


class RecordedFileSource:
    """A :class:`~flyknot_hw.mocap.stream.MocapSource` whose data arrive as a file.

    The lab's capture software records (started by the operator or by its own trigger) and
    writes a file into ``directory``. :meth:`start` notes the host time and the files already
    there; :meth:`stop` waits (up to ``wait_s``) for the trial's file (:func:`match_recording`:
    by ``trial_stem`` if set, else by time; only names matching ``pattern``; with
    ``new_only``, never a file that was already there, unchanged, at :meth:`start`) to appear
    and stop growing, then reads it.

    Args:
        directory: Where the capture software writes.
        trial_stem: Name of the trial's recording; None: match by time.
        pattern: Glob the file names must match (e.g. ``trial_*.c3d``); None: any.
        new_only: Skip files present and unchanged since :meth:`start` (the previous trial's
            recording must not be taken while this trial's is still being written).
        wait_s: How long :meth:`stop` waits for the file [s].
        poll_s: Interval of the directory polls [s].
        reader_kwargs: Passed to the reader (``body_labels`` or ``clusters`` for C3D,
            ``body_names``, ``clusters`` and ``units`` for CSV).
        clock: Wall clock (epoch seconds), injectable for tests.
    """

    def __init__(
        self,
        directory: str | Path,
        *,
        trial_stem: str | None = None,
        pattern: str | None = None,
        new_only: bool = True,
        wait_s: float = 30.0,
        poll_s: float = 0.2,
        reader_kwargs: Mapping[str, object] | None = None,
        clock: Callable[[], float] = time.time,
    ):
        check_positive("wait_s", wait_s)
        check_positive("poll_s", poll_s)
        self.directory = Path(directory)
        self.trial_stem = trial_stem
        self.pattern = pattern
        self.new_only = bool(new_only)
        self.wait_s = wait_s
        self.poll_s = poll_s
        self.reader_kwargs = dict(reader_kwargs or {})
        self._clock = clock
        self._t_start: float | None = None
        self._before: dict[str, tuple[int, int]] = {}
        self.last_path: Path | None = None

    @property
    def source(self) -> str:
        """The directory and pattern (for messages)."""
        return str(self.directory / (self.pattern or "*"))

    @property
    def recording(self) -> bool:
        """Whether :meth:`start` was called and :meth:`stop` has not returned a recording."""
        return self._t_start is not None

    def ready(self) -> None:
        """Check, before a trial moves the arm, that the directory exists."""
        if not self.directory.is_dir():
            raise HardwareError(
                f"mocap.file: the recordings directory {str(self.directory)!r} does not exist"
            )

    def start(self) -> None:
        """Note the trial's start time and the files already there (the capture software
        records on its own)."""
        self.ready()
        self._before = directory_snapshot(self.directory) if self.new_only else {}
        self._t_start = self._clock()

    def stop(self) -> RawStream:
        """Wait for the trial's recording and read it."""
        if self._t_start is None:
            raise HardwareError("RecordedFileSource.stop() called before start()")
        t_end = self._clock()
        deadline = time.monotonic() + self.wait_s
        last_err: HardwareError | None = None
        seen: tuple[Path, int] | None = None
        while True:
            try:
                path = match_recording(
                    self.directory,
                    trial_stem=self.trial_stem,
                    trial_start=self._t_start,
                    trial_end=t_end,
                    pattern=self.pattern,
                    exclude=self._before,
                )
                now = (path, path.stat().st_size)
                if now == seen and now[1] > 0:  # unchanged over one poll: written
                    self._t_start = None
                    self.last_path = path
                    return read_recording(path, **self.reader_kwargs)
                seen = now
            except (HardwareError, OSError) as e:
                last_err = e if isinstance(e, HardwareError) else HardwareError(str(e))
            if time.monotonic() > deadline:
                raise HardwareError(
                    f"no finished recording after {self.wait_s} s: {last_err}"
                ) from last_err
            time.sleep(self.poll_s)

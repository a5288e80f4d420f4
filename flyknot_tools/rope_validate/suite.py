"""The suite: every case on a rope model, full or quick, in parallel over ropes and variants."""

from __future__ import annotations

import json
import re
from collections.abc import Callable, Iterable, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import fields, replace
from pathlib import Path

from flyknot.errors import ConfigError
from flyknot_sim.rope_fields import FIELD, SETTABLE
from flyknot_sim.rope_table import RopeParams, SimSettings, load_sim_settings
from flyknot_tools.rope_validate.bench import RopeModel
from flyknot_tools.rope_validate.cases import (
    CaseResult,
    Swing,
    cantilever,
    capstan,
    knot_hold,
    lock_up,
    loop_spring_back,
    rest_after_motion,
    rest_shape,
    static_hold,
    stretch,
    swing_decay,
)

__all__ = [
    "CASE_NAMES",
    "SUITES",
    "model_with",
    "picture_path",
    "run_many",
    "run_suite",
    "table_markdown",
]

FULL_TAILS = (0.1, 0.2, 0.3)
FULL_SWINGS = (Swing(0.0), Swing(0.15, 0.7), Swing(0.3, 0.5))


def picture_path(pictures: str | Path | None, case: str, m: RopeModel) -> Path | None:
    """Where a case writes its picture of ``m``: ``<pictures>/<case>_rope<id>_<label>.png``
    (characters other than letters, digits, ``.``, ``_`` and ``-`` as ``_``); None: none."""
    if pictures is None:
        return None
    name = re.sub(r"[^A-Za-z0-9._-]+", "_", f"{case}_rope{m.params.id}_{m.label}")
    return Path(pictures) / f"{name}.png"


def _full(
    m: RopeModel, pictures: str | Path | None = None
) -> list[tuple[str, Callable[[], CaseResult]]]:
    rest = picture_path(pictures, "rest_after_motion", m)
    out = [
        ("rest_shape", lambda: rest_shape(m)),
        ("cantilever", lambda: cantilever(m)),
        ("spring_back", lambda: loop_spring_back(m)),
        ("swing_decay", lambda: swing_decay(m)),
        ("capstan", lambda: capstan(m)),
        ("static_hold", lambda: static_hold(m, seconds=60.0)),
        ("rest_after_motion", lambda: rest_after_motion(m, picture=rest)),
        ("lock_up", lambda: lock_up(m)),
        ("stretch", lambda: stretch(m)),
    ]
    for t in FULL_TAILS:
        for s in FULL_SWINGS:
            out.append(("knot_hold", lambda t=t, s=s: knot_hold(m, t, s)))
    return out


def _quick(
    m: RopeModel, pictures: str | Path | None = None
) -> list[tuple[str, Callable[[], CaseResult]]]:
    rest = picture_path(pictures, "rest_after_motion", m)
    return [
        ("rest_shape", lambda: rest_shape(m, seconds=3.0)),
        ("cantilever", lambda: cantilever(m, seconds=4.0)),
        ("spring_back", lambda: loop_spring_back(m)),
        ("capstan", lambda: capstan(m, seconds=2.0)),
        ("static_hold", lambda: static_hold(m, seconds=10.0, tighten_s=10.0)),
        ("knot_hold", lambda: knot_hold(m, 0.1, Swing(0.3, 0.5))),
        ("knot_hold", lambda: knot_hold(m, 0.1, Swing(0.15, 0.7))),
        ("rest_after_motion", lambda: rest_after_motion(m, picture=rest)),
        ("lock_up", lambda: lock_up(m)),
        ("stretch", lambda: stretch(m)),
    ]


SUITES = {"full": _full, "quick": _quick}
"""``full``: every case, the static hold over 60 s, the knot hold over tails 0.1/0.2/0.3 m x
no swing, +-0.15 m at 0.7 Hz, +-0.3 m at 0.5 Hz, the rest 10 s after the flying-knot throw.
``quick``: one of each but the swing decay (shorter), the knot hold with a 0.1 m tail swung
+-0.3 m at 0.5 Hz and +-0.15 m at 0.7 Hz. Each takes a directory for the cases' pictures
(:func:`picture_path`; None: none)."""

CASE_NAMES = (
    "knot_hold",
    "static_hold",
    "capstan",
    "cantilever",
    "spring_back",
    "swing_decay",
    "rest_shape",
    "rest_after_motion",
    "lock_up",
    "stretch",
)


def _coerce(name: str, text: str, current: object) -> object:
    """A ``[simulation]`` setting's value from its text, typed as its current value."""
    if isinstance(current, bool):
        if text not in ("true", "false"):
            raise ConfigError(name, f"must be true or false, got {text!r}")
        return text == "true"
    if isinstance(current, (int, float)) or current is None:
        try:
            value = float(text)
        except ValueError:
            raise ConfigError(name, f"must be a number, got {text!r}") from None
        return int(value) if isinstance(current, int) and value.is_integer() else value
    return text


def model_with(
    params: RopeParams,
    changes: Mapping[str, str],
    label: str | None = None,
    settings: SimSettings | None = None,
) -> RopeModel:
    """A :class:`RopeModel` of ``params`` with rope fields and ``[simulation]`` settings
    changed (``changes``: field name -> text, e.g. ``{"bend_hysteresis": "38", "cone":
    "elliptic"}``); rope fields win where a name is both. The rope fields are those of
    :data:`~flyknot_sim.rope_fields.SETTABLE`, each read as its declaration says
    (:meth:`~flyknot_sim.rope_fields.RopeField.from_text`). ``settings``: the
    ``[simulation]`` settings changed (None: those of ``assets/ropes.toml``).

    Raises:
        ConfigError: Unknown field (the valid names listed) or a bad value (the message
            names the field and its valid values).
    """
    sim_names = [f.name for f in fields(SimSettings)]
    rope_kw, sim_kw = {}, {}
    given = settings
    settings = load_sim_settings() if settings is None else settings
    for key, text in changes.items():
        if key in SETTABLE:
            rope_kw[key] = FIELD[key].from_text(text)
        elif key in sim_names:
            sim_kw[key] = _coerce(key, text, getattr(settings, key))
        else:
            raise ConfigError(
                "--set", f"unknown field {key!r}", sorted(SETTABLE + tuple(sim_names))
            )
    p = replace(params, **rope_kw)
    s = replace(settings, **sim_kw) if sim_kw else given
    text = ", ".join(f"{k}={v}" for k, v in changes.items())
    return RopeModel(p, settings=s, label=label or (text or "default"))


def run_suite(
    model: RopeModel,
    suite: str = "full",
    cases: Sequence[str] | None = None,
    pictures: str | Path | None = None,
) -> list[CaseResult]:
    """Every case of ``suite`` on ``model`` (only those named in ``cases``, if given); the
    cases that draw write their pictures into the directory ``pictures`` (None: none)."""
    if suite not in SUITES:
        raise ConfigError("suite", f"unknown suite {suite!r}", list(SUITES))
    for c in cases or ():
        if c not in CASE_NAMES:
            raise ConfigError("--cases", f"unknown case {c!r}", CASE_NAMES)
    jobs = SUITES[suite](model, pictures)
    return [run() for name, run in jobs if not cases or name in cases]


def _job(
    args: tuple[RopeModel, str, Sequence[str] | None, str | Path | None],
) -> list[CaseResult]:
    return run_suite(*args)


def run_many(
    models: Sequence[RopeModel],
    suite: str = "full",
    workers: int = 1,
    on_done: Callable[[list[CaseResult]], None] | None = None,
    cases: Sequence[str] | None = None,
    pictures: str | Path | None = None,
) -> list[CaseResult]:
    """:func:`run_suite` on every model (``workers`` processes), results in model order."""
    for c in cases or ():
        if c not in CASE_NAMES:
            raise ConfigError("--cases", f"unknown case {c!r}", CASE_NAMES)
    jobs = [(m, suite, cases, pictures) for m in models]
    if workers <= 1:
        results = []
        for job in jobs:
            results.append(_job(job))
            if on_done:
                on_done(results[-1])
    else:
        with ProcessPoolExecutor(workers) as pool:
            futures = [pool.submit(_job, j) for j in jobs]
            results = []
            for f in futures:
                results.append(f.result())
                if on_done:
                    on_done(results[-1])
    return [r for rs in results for r in rs]


def table_markdown(results: Iterable[CaseResult]) -> str:
    """One markdown table per rope and variant: case, expected, measured, pass; a count."""
    groups: dict[tuple, list[CaseResult]] = {}
    for r in results:
        groups.setdefault((r.rope, r.variant), []).append(r)
    out = []
    for (rope, variant), rs in groups.items():
        judged = [r for r in rs if r.applies]
        passed = sum(r.passed for r in judged)
        out.append(f"### rope {rope} ({variant}): {passed}/{len(judged)} passed\n")
        out.append("| case | expected | measured | result |")
        out.append("|---|---|---|---|")
        for r in rs:
            verdict = ("pass" if r.passed else "FAIL") if r.applies else "reported"
            out.append(f"| {r.case} | {r.expected} | {r.detail} | {verdict} |")
        out.append("")
    return "\n".join(out)


def results_json(results: Iterable[CaseResult]) -> str:
    """The results as a JSON list."""
    return json.dumps([r.to_json() for r in results], indent=1, default=float)

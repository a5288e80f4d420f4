"""Progress bars that stay quiet when nobody watches them."""

from __future__ import annotations


def bar_disable(progress: bool) -> bool | None:
    """The ``disable`` argument for :class:`tqdm.tqdm`: off when ``progress`` is False, and
    otherwise tqdm's ``None`` (shown on a terminal, silent when the output is a file or a pipe,
    so logs hold no escape codes)."""
    return None if progress else True

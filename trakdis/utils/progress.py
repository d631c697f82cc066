"""Progress bars (tqdm) with one switch for quiet runs and tests."""
from __future__ import annotations

import os
from typing import Iterable

from tqdm.auto import tqdm

__all__ = ["progress"]


def progress(iterable: Iterable | None = None, *, total: int | None = None, desc: str | None = None,
             initial: int = 0, disable: bool | None = None, **kwargs) -> tqdm:
    """A tqdm bar on stderr. ``TRAKDIS_NO_PROGRESS=1`` or ``disable=True`` turns it off.

    ``initial`` lets a resumed loop start the bar where the checkpoint left off.
    """
    if disable is None:
        disable = os.environ.get("TRAKDIS_NO_PROGRESS", "0") not in ("", "0")
    return tqdm(iterable, total=total, desc=desc, initial=initial, disable=disable,
                dynamic_ncols=True, leave=False, **kwargs)

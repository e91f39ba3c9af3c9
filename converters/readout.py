"""The rolling-shutter readout a converter records for a camera it knows nothing about.

Bags and ScanNet scenes name no readout, so unless ``--readout`` gives one the store records it
as unknown (`READOUT_UNKNOWN`) and `bgs run` estimates it from the frames (docs/method.md §6);
``--readout auto`` says the same explicitly.
"""

from __future__ import annotations

import math

from bgs_batch.store import READOUT_UNKNOWN


def stored_readout(option: float | None) -> float:
    """The readout to store for ``--readout`` (None when not given; NaN for ``auto``)."""
    return READOUT_UNKNOWN if option is None else option


def readout_source(option: float | None, why_unknown: str) -> str:
    """The provenance of the stored readout: ``--readout``, or why `bgs run` estimates it."""
    if option is None or math.isnan(option):
        return f"unknown: `bgs run` estimates it from the frames ({why_unknown})"
    return "--readout"

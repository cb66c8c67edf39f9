"""The Novint Falcon back-end, over pyusb without the vendor SDK.

``protocol`` (wire format), ``kinematics`` (numba kernels) and ``firmware`` (image checks)
import without pyusb; ``FalconDevice`` (in ``device``) needs it and is loaded on first use.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .device import FalconDevice

__all__ = ["FalconDevice"]


def __getattr__(name: str) -> Any:
    if name == "FalconDevice":
        from .device import FalconDevice

        return FalconDevice
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

"""The model's sensitivities: the columns of the calibration's linear least-squares problem.

Every force component of the model is ``Us·(a + K·b)``: the tangential forces scale with Us and
the normal forces with Us·K (model.md). ``a`` is a case's components at Us = 1, K = 0 and ``b``
the extra at K = 1; both come from the model itself, so whatever the kernel does (spin, element
geometry) the fit sees exactly.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..model.cases import CuttingCase
from ..model.cutting import CuttingModel
from ..model.params import CuttingParams, Spin

#: Burr resolution for calibration: a few hundred evaluations, so afford 0.1 % accuracy
#: (benchmarks/model.md: 48 × 96 elements, refine 3, well under the default's 0.3 %).
CALIB_N_THETA = 48


@dataclass(frozen=True)
class ModelSetup:
    """What the fit does not estimate: the spin direction and the minimum cutting speed."""

    spin: Spin = "forward"
    min_cutting_rpm: float = CuttingParams.min_cutting_rpm


class Sensitivities:
    """Per case: ``a`` (3,) and ``b`` (3,), N per N/mm² — feed, lateral, normal.

    Caches one model per burr radius and one result per case.
    """

    def __init__(self, setup: ModelSetup | None = None, n_theta: int = CALIB_N_THETA) -> None:
        self.setup = setup if setup is not None else ModelSetup()
        self.n_theta = n_theta
        self._models: dict[float, CuttingModel] = {}
        self._cache: dict[CuttingCase, tuple[np.ndarray, np.ndarray]] = {}

    def _model(self, radius_mm: float) -> CuttingModel:
        model = self._models.get(radius_mm)
        if model is None:
            params = CuttingParams(us_n_mm2=1.0, k=0.0, radius_mm=radius_mm,
                                   spin=self.setup.spin,
                                   min_cutting_rpm=self.setup.min_cutting_rpm)
            model = self._models[radius_mm] = CuttingModel(params, n_theta=self.n_theta)
        return model

    def of(self, case: CuttingCase) -> tuple[np.ndarray, np.ndarray]:
        """(a, b) for one case.

        Raises:
            ValueError: the spindle is below the minimum cutting speed (the model predicts no
                cutting force, so the case cannot inform Us).
        """
        cached = self._cache.get(case)
        if cached is not None:
            return cached
        if abs(case.rpm) < self.setup.min_cutting_rpm:
            raise ValueError(
                f"{case.orientation} {case.angle_deg:g}°: {case.rpm:g} rpm is below the minimum "
                f"cutting speed {self.setup.min_cutting_rpm:g} rpm, where the model does not cut")
        model = self._model(case.radius_mm)
        args = (case.centre_mm, case.axis, case.feed_velocity_mm_s, case.rpm)
        model.params = model.params.with_(k=0.0)
        r0 = model.evaluate(*args)
        model.params = model.params.with_(k=1.0)
        r1 = model.evaluate(*args)
        a = np.array([r0.feed_N, r0.lateral_N, r0.normal_N])
        b = np.array([r1.feed_N, r1.lateral_N, r1.normal_N]) - a
        self._cache[case] = (a, b)
        return a, b

    def matrices(self, cases: Sequence[CuttingCase]) -> tuple[np.ndarray, np.ndarray]:
        """(A, B), each (n, 3): the sensitivities of every case, in order."""
        if not cases:
            return np.zeros((0, 3)), np.zeros((0, 3))
        pairs = [self.of(c) for c in cases]
        return np.array([p[0] for p in pairs]), np.array([p[1] for p in pairs])

    def predict(self, cases: Sequence[CuttingCase], us_n_mm2: float, k: float) -> np.ndarray:
        """(n, 3) model components for these cases at Us, K."""
        a, b = self.matrices(cases)
        return us_n_mm2 * (a + k * b)

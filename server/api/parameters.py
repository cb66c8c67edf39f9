"""Changing a session's settings over REST: parameters, features, materials, calibrations.

Each change is computed as the session's new :class:`~.sessions.Settings` first (``settings``:
validated, nothing touched), sent to the hot loop (``WorkerPool.push``), and only then taken
by the session whole: a change the loop refuses leaves the session as it was, with nothing to
roll back. Raises the domain errors of ``errors``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, replace

from ..bone import Material
from .errors import Conflict, Invalid, NotFound
from .models import Features, Parameters
from .sessions import ManagedSession, Settings
from .settings import settle, with_material
from .workers import WorkerPool

#: Parameters a device loop converts its poses with: not changed under a running one.
PLACEMENT_FIELDS = ("frame", "placement_position", "placement_orientation")


class SessionSettings:
    """Applies settings changes to sessions and their hot loops.

    Args:
        pool: the hot loops.
        device_attached: whether a device loop drives a session (by id).
    """

    def __init__(self, pool: WorkerPool, device_attached: Callable[[int], bool]) -> None:
        self.pool = pool
        self.device_attached = device_attached

    def _take(self, session: ManagedSession, new: Settings, materials: bool = False) -> None:
        """The loop first, then the session (call with the session's lock held)."""
        self.pool.push(session, new, materials=materials)
        session.settings = new

    def update_parameters(self, session: ManagedSession, p: Parameters) -> ManagedSession:
        """Change the fields ``p`` sets, all or none.

        Raises:
            Conflict: a placement change while a device loop drives the session.
            Invalid: a field does not fit.
        """
        changed = [k for k in PLACEMENT_FIELDS
                   if getattr(p, k) is not None and getattr(p, k) != getattr(session.config, k)]
        if changed and self.device_attached(session.id):
            # The device loop converts its poses with the frame and placement it started
            # with: changing them under it would misplace the burr and misread k and b.
            raise Conflict(f"session {session.id} drives a device: detach it (DELETE "
                           f"…/device) before changing {', '.join(changed)}")
        with session.lock:
            current = session.settings
            # The bone's voxels are checked once one is loaded (at its load otherwise).
            spacing = session.ref.spacing_mm if session.ref is not None else (0.0,)
            new = settle(current, p, spacing)
            self._take(session, new, materials=new.materials is not current.materials)
        return session

    def update_features(self, session: ManagedSession, features: Features) -> ManagedSession:
        with session.lock:
            self._take(session, replace(session.settings, features=features))
        return session

    def set_material(self, session: ManagedSession, label: int, material: Material | None,
                     changes: dict | None = None) -> ManagedSession:
        """Set material ``label`` of a ready session (``material``, or ``changes`` to its
        fields). NotFound: ``changes`` for a label the bone lacks; Invalid: a bad value."""
        with session.lock:
            self._take(session, with_material(session.settings, label, material, changes),
                       materials=True)
        return session

    @staticmethod
    def calibration_target(session: ManagedSession, label: int | None
                           ) -> tuple[int, Material]:
        """The material a calibration would set: ``label``, default the primary."""
        label = session.primary_label if label is None else label
        if label is None:
            raise Invalid("the session's bone has no primary material: give label")
        assert session.materials is not None
        if label not in session.materials:
            raise NotFound(f"no material with label {label}")
        return label, session.materials[label]

    def apply_calibration(self, session: ManagedSession, label: int, us_n_mm2: float,
                          k: float | None, fit: dict | None, provenance: dict | None) -> dict:
        """Set material ``label``'s Us and K (None: keep its K) and keep a record of it with
        the fit's summary (``fit``) or the caller's ``provenance``."""
        with session.lock:  # re-entrant: set_material takes it too
            assert session.materials is not None
            before = session.materials[label]
            k = before.k if k is None else k
            if not 0.0 <= k <= 100.0:
                raise Invalid(f"the fitted K = {k:.4g} is outside [0, 100], which the model "
                              "cannot take: fit Us alone with K fixed")
            self.set_material(session, label, None, {"us_n_mm2": us_n_mm2, "k": k})
            after = session.materials[label]
            record = {
                "label": label, "material": after.name, "us_n_mm2": after.us_n_mm2,
                "k": after.k, "previous": {"us_n_mm2": before.us_n_mm2, "k": before.k},
                "fit": fit, "provenance": provenance, "applied_s": time.time(),
            }
            session.calibrations = {**session.calibrations, label: record}
        return {"label": label, "material": asdict(after), "calibration": record}

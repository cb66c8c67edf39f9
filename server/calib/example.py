"""An example folder of synthetic dynamometer recordings of known truth.

The thesis's nine cases (model.md) × replicates, each the model's force at the true Us and K,
scattered from replicate to replicate as real runs are, then recorded as a Kistler-like
dynamometer under the bone would: the force on the workpiece, 3 kHz, the spindle's 1 kHz tone,
noise, a drifting charge amplifier, free spinning before and after the cut.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..model.cases import thesis_cases
from ..model.params import THESIS_K, THESIS_US_N_MM2
from .design import Sensitivities
from .folder import MANIFEST, component_basis
from .recording import save_recording
from .synthetic import synthetic_recording
from .table import COLUMNS, CaseRow, write_case_table

TRUTH = "truth.json"


@dataclass(frozen=True)
class ExampleFolder:
    path: Path
    manifest: Path
    count: int
    us_n_mm2: float
    k: float


def write_example(folder: str | Path, *, us_n_mm2: float = THESIS_US_N_MM2,
                  k: float = THESIS_K, replicates: int = 5, scatter: float = 0.08,
                  tone_N: float = 0.4, noise_N: float = 0.1, drift_N_s: float = 0.02,
                  seed: int = 1) -> ExampleFolder:
    """Write ``case-NN-rR.csv`` recordings, ``manifest.csv`` and ``truth.json`` (the true Us, K
    and each replicate's true mean components on the burr) into ``folder``.

    ``scatter`` is the replicate-to-replicate relative spread of the whole force (real runs
    differ by more than their noise); ``tone_N`` the spindle's per-axis vibration amplitude.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    sens = Sensitivities()
    cases = list(thesis_cases())
    model = sens.predict(cases, us_n_mm2, k)
    manifest_rows, truth_rows = [], []
    for i, (case, components) in enumerate(zip(cases, model, strict=True)):
        basis = component_basis(case.feed_direction, np.array([0.0, 0.0, 1.0]))
        for r in range(replicates):
            true = components * (1.0 + scatter * rng.standard_normal())
            on_workpiece = -(basis.T @ true)
            name = f"case-{i + 1:02d}-r{r + 1}.csv"
            rec = synthetic_recording(
                on_workpiece, sample_rate_hz=3000.0, spindle_hz=case.rpm / 60.0,
                tone_amplitude_N=rng.uniform(0.7, 1.0, 3) * tone_N, noise_N=noise_N,
                drift_N_s=rng.uniform(-1.0, 1.0, 3) * drift_N_s,
                offset_N=rng.uniform(-0.05, 0.05, 3), free_s=0.4, burring_s=1.2, ramp_s=0.05,
                seed=int(rng.integers(1 << 31)))
            # A DAQ's 0.1 mN resolution: short CSV lines, nothing the fit can notice.
            save_recording(folder / name, replace(rec, force_N=np.round(rec.force_N, 4)))
            manifest_rows.append({"file": name, **{c: v for c, v in CaseRow(
                case, 0.0, 0.0, 0.0).as_dict().items() if c in COLUMNS[:6]}})
            truth_rows.append(CaseRow(case, *true.tolist(), source=name))
    manifest = folder / MANIFEST
    columns = ["file", *COLUMNS[:6]]
    lines = [",".join(columns)] + [",".join(str(m[c]) for c in columns) for m in manifest_rows]
    manifest.write_text("\n".join(lines) + "\n", encoding="utf-8")
    write_case_table(folder / "truth-cases.csv", truth_rows)
    (folder / TRUTH).write_text(json.dumps({
        "us_n_mm2": us_n_mm2, "k": k, "replicates": replicates, "scatter": scatter,
        "tone_N": tone_N, "noise_N": noise_N, "drift_N_s": drift_N_s, "seed": seed,
        "note": "truth-cases.csv holds each recording's true mean force on the burr",
    }, indent=2) + "\n", encoding="utf-8")
    return ExampleFolder(folder, manifest, len(manifest_rows), us_n_mm2, k)

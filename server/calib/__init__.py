"""Calibrating ``Us`` and ``K`` from dynamometer data (thesis chapters II–III, model.md).

- :mod:`.recording`: 3-axis force recordings (CSV, NPZ) in and out.
- :mod:`.signal`: burring/non-burring segments, mean force, vibration amplitude (the thesis's
  peak method and a least-squares sinusoid fit), dominant frequency.
- :mod:`.synthetic`: recordings of known truth, for tests and the example dataset.
- :mod:`.table`: the case table (one row per replicate: case geometry and mean force
  components).
- :mod:`.folder`: a folder of recordings with a manifest → a case table.
- :mod:`.design`: the model's sensitivities, the columns of the linear least-squares problem.
- :mod:`.fit`: Us, or Us and K, with confidence intervals, residuals and cross-validation.
- :mod:`.plot`: the thesis's Fig. 19/20 — measurements as box plots, the fitted model as curves.
"""

"""A folder of recordings → a case table → Us and K: the issue's recovery numbers on synthetic
recordings of known truth (a mean shift, a 1 kHz tone sampled at 3 kHz, noise, drift), the
manifest's options, and bad folders."""

from __future__ import annotations

import json

import numpy as np
import pytest

from burrforce.server.calib.design import Sensitivities
from burrforce.server.calib.example import write_example
from burrforce.server.calib.fit import FitOptions, calibrate
from burrforce.server.calib.folder import (
    FolderError,
    component_basis,
    parse_axis,
    process_folder,
)
from burrforce.server.calib.recording import save_recording
from burrforce.server.calib.synthetic import synthetic_recording
from burrforce.server.calib.table import read_case_table
from burrforce.server.cli import main
from burrforce.server.model import CuttingCase

US, K = 805.1, 1.3


def test_noise_free_recordings_give_back_us_within_a_thousandth_of_a_percent(tmp_path):
    """Tone, drift and offsets but no noise and no replicate scatter: the issue asks for 1 %."""
    write_example(tmp_path, replicates=2, scatter=0.0, noise_N=0.0, drift_N_s=0.05)
    cal = calibrate(process_folder(tmp_path).rows, FitOptions())
    assert cal.estimate.us == pytest.approx(US, rel=1e-5)
    assert cal.estimate.k == pytest.approx(K, rel=1e-5)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_noisy_recordings_give_us_and_k_inside_their_intervals(tmp_path, seed):
    write_example(tmp_path, replicates=3, seed=seed)
    result = process_folder(tmp_path)
    est = calibrate(result.rows, FitOptions()).estimate
    assert est.us_ci[0] < US < est.us_ci[1]
    assert est.k_ci[0] < K < est.k_ci[1]
    # Each recording's components against its own truth, in its own standard errors.
    truth = {r.source: r for r in read_case_table(tmp_path / "truth-cases.csv")}
    z = np.array([(r.row.forces_N - truth[r.row.source].forces_N) / r.components_sem_N
                  for r in result.reports])
    assert np.abs(z).max() < 5.0 and 0.6 < z.std() < 1.5


def test_the_cli_turns_a_recording_folder_into_us_k_a_table_and_a_plot(tmp_path, capsys):
    write_example(tmp_path / "runs", replicates=3, seed=4)
    plot, table = tmp_path / "fit.png", tmp_path / "table.csv"
    assert main(["calibrate", "--recordings", str(tmp_path / "runs"), "--json", "--plot",
                 str(plot), "--table-out", str(table)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["us_ci"][0] < US < out["us_ci"][1]
    assert len(out["recordings"]) == 27 and out["failures"] == []
    first = out["recordings"][0]
    assert first["dominant_frequency_hz"] == pytest.approx(1000.0, abs=0.5)
    assert first["ratio_fit"] == pytest.approx(1.0, abs=0.05)
    # The thesis's peak-picking reads a 1 kHz tone at 3 kHz low; the fit does not.
    assert first["vibration_free_peaks_N"] < 0.9 * first["vibration_free_N"]
    assert out["vibration"]["fd_N"] == pytest.approx(0.4 * 0.85 * np.sqrt(3), rel=0.15)
    assert out["vibration"]["g"] < 0.2
    assert [r.source for r in read_case_table(table)] == [r["source"] for r in out["recordings"]]
    assert plot.stat().st_size > 10_000


def _folder(tmp_path, components_on_burr, *, case=None, manifest_extra="", name="run.npz",
            **kwargs):
    """One recording of a case with known force components on the burr, in the dynamometer
    frame the manifest's extra columns describe (default: the case's own)."""
    case = case or CuttingCase("parallel", 60.0)
    feed_axis = kwargs.pop("feed_axis", case.feed_direction)
    normal_axis = kwargs.pop("normal_axis", np.array([0.0, 0.0, 1.0]))
    sign = -1.0 if kwargs.pop("forces_on", "workpiece") == "workpiece" else 1.0
    basis = component_basis(np.asarray(feed_axis, float), np.asarray(normal_axis, float))
    rec = synthetic_recording(sign * (basis.T @ np.asarray(components_on_burr)),
                              noise_N=0.0, seed=0, **kwargs)
    save_recording(tmp_path / name, rec)
    header = "file,orientation,angle_deg,depth_mm,feed_mm_s,rpm,radius_mm"
    row = f"{name},{case.orientation},{case.angle_deg},0.5,3,60000,2"
    extra_header, extra_row = manifest_extra.split("|") if manifest_extra else ("", "")
    (tmp_path / "manifest.csv").write_text(
        f"{header}{extra_header}\n{row}{extra_row}\n")
    return tmp_path


def test_a_rotated_dynamometer_is_described_by_its_axes(tmp_path):
    """The feed ran along the dynamometer's −y and the surface faced its +x."""
    truth = np.array([-0.5, 0.05, 0.9])
    folder = _folder(tmp_path, truth, manifest_extra=',feed_axis,normal_axis|,-y,x',
                     feed_axis=(0, -1, 0), normal_axis=(1, 0, 0))
    (report,) = process_folder(folder).reports
    assert np.allclose(report.row.forces_N, truth, atol=1e-6)
    assert report.as_dict()["forces_on"] == "workpiece"


def test_forces_already_on_the_burr_are_taken_as_they_are(tmp_path):
    truth = np.array([-0.5, 0.05, 0.9])
    folder = _folder(tmp_path, truth, manifest_extra=",forces_on|,burr", forces_on="burr")
    assert np.allclose(process_folder(folder).rows[0].forces_N, truth, atol=1e-6)
    assert np.allclose(process_folder(folder, forces_on="burr").rows[0].forces_N, truth,
                       atol=1e-6)


def test_without_a_manifest_the_case_comes_from_the_files(tmp_path):
    case = CuttingCase("diagonal", 30.0)
    basis = component_basis(case.feed_direction, np.array([0.0, 0.0, 1.0]))
    meta = {"orientation": "diagonal", "angle_deg": 30.0, "depth_mm": 0.5, "feed_mm_s": 3.0,
            "rpm": 60000.0, "radius_mm": 2.0}
    for name in ("a.npz", "b.csv"):
        save_recording(tmp_path / name, synthetic_recording(
            -(basis.T @ np.array([-0.34, -0.11, 0.22])), seed=1, metadata=meta))
    rows = process_folder(tmp_path).rows
    assert [r.source for r in rows] == ["a.npz", "b.csv"]
    assert all(r.case == case for r in rows)
    assert np.allclose(rows[1].forces_N, [-0.34, -0.11, 0.22], atol=1e-6)


def test_a_stronger_burring_vibration_shows_in_the_ratio_and_the_gain(tmp_path):
    folder = _folder(tmp_path, [-0.5, 0.05, 0.9], burring_tone_gain=1.5)
    result = process_folder(folder)
    assert result.reports[0].analysis.ratio_fit == pytest.approx(1.5, rel=0.01)
    v = result.vibration()
    free, force = v["fd_N"], np.linalg.norm([-0.5, 0.05, 0.9])
    assert v["g"] == pytest.approx(np.sqrt((1.5 * free) ** 2 - free ** 2) / force, rel=0.02)


def test_every_bad_recording_is_listed_and_skip_bad_keeps_the_rest(tmp_path):
    write_example(tmp_path, replicates=1, seed=2)
    (tmp_path / "case-02-r1.csv").write_text("fx,fy,fz\n1,2\n")
    manifest = (tmp_path / "manifest.csv").read_text().splitlines()
    manifest[3] = manifest[3].replace("parallel", "sideways")
    (tmp_path / "manifest.csv").write_text("\n".join(manifest) + "\n")
    with pytest.raises(FolderError) as exc:
        process_folder(tmp_path)
    message = str(exc.value)
    assert message.startswith("2 of 9 recording(s) failed")
    assert "case-02-r1.csv" in message and "sideways" in message
    result = process_folder(tmp_path, skip_bad=True)
    assert len(result.rows) == 7 and len(result.failures) == 2


@pytest.mark.parametrize("manifest, message", [
    ("file\nrun.npz\n", "no orientation, angle_deg"),
    ("name,orientation\nrun.npz,parallel\n", "needs a 'file' column"),
    ("file,orientation,angle_deg,depth_mm,feed_mm_s,rpm,radius_mm\n"
     "gone.npz,parallel,30,0.5,3,60000,2\n", "gone.npz"),
    ("file,orientation,angle_deg,depth_mm,feed_mm_s,rpm,radius_mm,feed_axis\n"
     "run.npz,parallel,30,0.5,3,60000,2,sideways\n", "feed_axis must be x, y, z"),
    ("file,orientation,angle_deg,depth_mm,feed_mm_s,rpm,radius_mm,feed_axis\n"
     "run.npz,parallel,30,0.5,3,60000,2,z\n", "not perpendicular to the surface normal"),
    ("file,orientation,angle_deg,depth_mm,feed_mm_s,rpm,radius_mm,forces_on\n"
     "run.npz,parallel,30,0.5,3,60000,2,hand\n", "forces_on must be workpiece or burr"),
    ("file,orientation,angle_deg,depth_mm,feed_mm_s,rpm,radius_mm\n"
     "run.npz,parallel,30,0.5,3,60000,2\nrun.npz,parallel,30,0.5,3,60000,2\n", "listed twice"),
    ("file,orientation,angle_deg,depth_mm,feed_mm_s,rpm,radius_mm\n"
     "run.npz,parallel,30,0.5,3,60000,2,oops\n", "8 cells, the header has 7"),
    ("file,orientation,angle_deg,depth_mm,feed_mm_s,rpm,radius_mm,sample_rate_hz\n"
     "run.npz,parallel,30,0.5,3,60000,2,fast\n", "sample_rate_hz is not a number: 'fast'"),
])
def test_bad_manifests_say_what_is_wrong(tmp_path, manifest, message):
    save_recording(tmp_path / "run.npz", synthetic_recording([0.3, 0.0, -0.8], seed=0))
    (tmp_path / "manifest.csv").write_text(manifest)
    with pytest.raises(FolderError, match=message):
        process_folder(tmp_path)


def test_a_semicolon_manifest_takes_decimal_commas(tmp_path):
    folder = _folder(tmp_path, [-0.5, 0.05, 0.9])
    text = (folder / "manifest.csv").read_text().replace(",", ";").replace("0.5", "0,5")
    (folder / "manifest.csv").write_text(text)
    assert process_folder(folder).rows[0].case.depth_mm == 0.5


def test_a_recording_without_the_spindle_tone_is_flagged_and_its_json_stays_valid(tmp_path,
                                                                                  capsys):
    _folder(tmp_path, [-0.5, 0.05, 0.9], tone_amplitude_N=(0.0, 0.0, 0.0))
    rows = (tmp_path / "manifest.csv").read_text().splitlines()
    (tmp_path / "manifest.csv").write_text("\n".join(
        [rows[0], rows[1], rows[1].replace("run.npz", "run2.npz")]) + "\n")
    save_recording(tmp_path / "run2.npz", synthetic_recording(
        -(component_basis(np.array([1.0, 0, 0]), np.array([0, 0, 1.0])).T
          @ np.array([-0.5, 0.05, 0.9])) * 1.02, tone_amplitude_N=(0.0, 0.0, 0.0), seed=3))
    assert main(["calibrate", "--recordings", str(tmp_path), "--fit", "us", "--json"]) == 0

    def refuse(constant):
        raise AssertionError(f"{constant} in the JSON")

    out = json.loads(capsys.readouterr().out, parse_constant=refuse)
    assert any("not the spindle's 1000 Hz" in w for w in out["recording_warnings"])


def test_an_empty_folder_is_refused(tmp_path):
    with pytest.raises(FolderError, match=r"holds no \.csv or \.npz recordings"):
        process_folder(tmp_path)
    with pytest.raises(FolderError, match="no manifest at"):
        process_folder(tmp_path, manifest=tmp_path / "m.csv")


def test_axes_parse_names_signs_and_vectors():
    assert parse_axis("-Y", "a").tolist() == [0.0, -1.0, 0.0]
    assert np.allclose(parse_axis("1 1 0", "a"), [np.sqrt(0.5), np.sqrt(0.5), 0.0])
    with pytest.raises(ValueError, match="three numbers"):
        parse_axis("0 0 0", "a")


def test_the_example_is_the_thesis_table_at_its_us(tmp_path):
    folder = write_example(tmp_path, replicates=1, scatter=0.0)
    assert folder.count == 9 and (tmp_path / "truth.json").exists()
    truth = read_case_table(tmp_path / "truth-cases.csv")
    model = Sensitivities().predict([r.case for r in truth], US, K)
    assert np.allclose([r.forces_N for r in truth], model)

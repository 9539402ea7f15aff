"""The reduced length model (models/length_fits.json, evaluated by spindle.chain.length_model).

Accuracy is checked against the exact MuJoCo length model on a grid other than the one the
fits were made on, and against the OpenSim oracle; bad angles and a missing, malformed or
stale json must fail loudly and name the regenerating command.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from proprio_env.body.model import model_path
from spindle.chain import MUSCLES
from spindle.chain.length_model import (
    REGENERATE_COMMAND,
    LengthFitsError,
    default_fits_path,
    file_sha256,
    load_length_fits,
)

REPO = Path(__file__).resolve().parents[1]
ORACLE = Path(__file__).parent / "data" / "arm26_elbow_oracle.csv"


def read_oracle() -> dict[str, np.ndarray]:
    lines = [ln for ln in ORACLE.read_text().splitlines() if ln and not ln.startswith("#")]
    table = np.array([[float(v) for v in ln.split(",")] for ln in lines[1:]])
    return {name: table[:, i] for i, name in enumerate(lines[0].split(","))}


@pytest.fixture(scope="module")
def fits():
    return load_length_fits()


def test_committed_fits_match_committed_model(fits):
    assert default_fits_path().parent == model_path().parent
    assert fits.model_sha256 == file_sha256(model_path())
    assert fits.muscles == MUSCLES


def test_valid_range_covers_0_to_130_deg(fits):
    lo, hi = fits.valid_range_rad
    assert lo <= 0.0 and hi >= np.radians(130.0)
    assert np.all(np.isfinite(fits.length_L0(np.radians([0.0, 65.0, 130.0]))))


def test_fit_within_0_001_L0_of_exact_model(fits):
    from proprio_env.body.model import load_model
    from proprio_env.body.muscle_length import sweep

    # 0.0137 deg steps, offset from the 0.05 deg fitting grid.
    lo, hi = fits.valid_range_rad
    angle = np.linspace(lo, hi, 9491)
    exact = sweep(load_model(), angle)
    assert exact.muscles == fits.muscles
    error = fits.length_L0(angle) - exact.fibre_length_L0
    assert np.max(np.abs(error)) <= 1e-3
    for j, name in enumerate(fits.muscles):
        # the recorded max error is honest (to within the grid's resolution)
        assert np.max(np.abs(error[:, j])) <= fits[name].max_error_L0 * 1.05


def test_fit_matches_opensim_passive_equilibrium():
    fits = load_length_fits()
    oracle = read_oracle()
    fitted = fits.length_L0(oracle["elbow_flex_rad"])
    for j, name in enumerate(MUSCLES):
        assert np.max(np.abs(fitted[:, j] - oracle[f"{name}_norm_fiber_length"])) <= 0.005


def test_fit_slope_matches_opensim(fits):
    oracle = read_oracle()
    angle = oracle["elbow_flex_rad"]
    velocity = fits.velocity_L0_s(angle[1:-1], np.ones(angle.size - 2))
    for j, name in enumerate(MUSCLES):
        slope = np.gradient(oracle[f"{name}_rigid_norm_fiber_length"], angle)[1:-1]
        assert np.max(np.abs(velocity[:, j] - slope)) <= 0.015  # L0/s at 1 rad/s


def test_shapes_are_vectorised_over_leading_axes(fits):
    assert fits.length_L0(0.3).shape == (2,)
    assert fits.length_L0(np.full(7, 0.3)).shape == (7, 2)
    assert fits.length_L0(np.full((4, 3), 0.3)).shape == (4, 3, 2)
    assert fits.velocity_L0_s(np.full(5, 0.3), np.full(5, 2.0)).shape == (5, 2)
    np.testing.assert_allclose(
        fits.velocity_L0_s(0.3, 2.0), 2.0 * np.array([f.derivative_L0_rad(0.3) for f in fits.fits])
    )


@pytest.mark.parametrize("bad", [np.nan, np.inf, -1e-3, np.radians(130.0) + 1e-3])
def test_bad_angle_raises(fits, bad):
    with pytest.raises(ValueError, match="elbow angle"):
        fits.length_L0(np.array([0.5, bad]))
    with pytest.raises(ValueError, match="elbow angle"):
        fits["BRA"].length_L0(bad)


def test_clip_clamps_to_range_but_not_nan(fits):
    lo, hi = fits.valid_range_rad
    np.testing.assert_array_equal(
        fits.length_L0(np.array([lo - 0.1, hi + 0.1]), clip=True),
        fits.length_L0(np.array([lo, hi])),
    )
    with pytest.raises(ValueError, match="finite"):
        fits.length_L0(np.nan, clip=True)
    with pytest.raises(ValueError, match="finite"):
        fits.velocity_L0_s(0.5, np.nan)


def _copy_fits(tmp_path: Path) -> tuple[Path, Path]:
    xml = tmp_path / "elbow.xml"
    js = tmp_path / "length_fits.json"
    shutil.copy(model_path(), xml)
    shutil.copy(default_fits_path(), js)
    return xml, js


def test_missing_json_names_the_command(tmp_path):
    with pytest.raises(LengthFitsError, match="does not exist") as err:
        load_length_fits(tmp_path / "length_fits.json")
    assert REGENERATE_COMMAND in str(err.value)


@pytest.mark.parametrize(
    "corrupt",
    [
        lambda doc: "{ not json",
        lambda doc: json.dumps([1, 2]),
        lambda doc: json.dumps({**doc, "format": "something else"}),
        lambda doc: json.dumps({k: v for k, v in doc.items() if k != "muscles"}),
        lambda doc: json.dumps({**doc, "valid_range_rad": [1.0, 0.0]}),
        lambda doc: json.dumps({**doc, "muscles": {}}),
        lambda doc: json.dumps(
            {**doc, "muscles": {"BRA": {**doc["muscles"]["BRA"], "coefficients": ["x"]}}}
        ),
        lambda doc: json.dumps(
            {**doc, "muscles": {"BRA": {**doc["muscles"]["BRA"], "coefficients": []}}}
        ),
        lambda doc: json.dumps({**doc, "model_sha256": "abc"}),
    ],
)
def test_malformed_json_names_the_command(tmp_path, corrupt):
    _, js = _copy_fits(tmp_path)
    js.write_text(corrupt(json.loads(js.read_text())))
    with pytest.raises(LengthFitsError, match="malformed") as err:
        load_length_fits(js)
    assert REGENERATE_COMMAND in str(err.value)


def test_non_finite_coefficient_is_malformed(tmp_path):
    _, js = _copy_fits(tmp_path)
    js.write_text(
        js.read_text().replace('"coefficients": [\n        ', '"coefficients": [NaN, ', 1)
    )
    with pytest.raises(LengthFitsError, match="malformed"):
        load_length_fits(js)


def test_stale_json_names_the_command(tmp_path):
    xml, js = _copy_fits(tmp_path)
    load_length_fits(js)  # the untouched copy is fine
    xml.write_bytes(xml.read_bytes().replace(b'range="0 2.26892803"', b'range="0 2.2"', 1))
    with pytest.raises(LengthFitsError, match="stale") as err:
        load_length_fits(js)
    assert REGENERATE_COMMAND in str(err.value)
    load_length_fits(js, verify=False)  # a device without the model may skip the check


def test_unverifiable_json_is_refused(tmp_path):
    js = tmp_path / "length_fits.json"
    shutil.copy(default_fits_path(), js)
    with pytest.raises(LengthFitsError, match="staleness"):
        load_length_fits(js)
    load_length_fits(js, model_xml=model_path())


def _run(code: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run(
        [sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True, text=True
    )


def test_spindle_evaluates_fits_without_mujoco():
    done = _run(
        "import sys; from spindle.chain.length_model import load_length_fits;"
        "print(load_length_fits().length_L0(0.5));"
        "assert 'mujoco' not in sys.modules and 'proprio_env' not in sys.modules"
    )
    assert done.returncode == 0, done.stderr


def test_fit_script_regenerates_the_committed_fits(tmp_path):
    out = tmp_path / "length_fits.json"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    done = subprocess.run(
        [sys.executable, "scripts/fit_lengths.py", "--fits", str(out), "--no-figure"],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
    )
    assert done.returncode == 0, done.stderr
    new = json.loads(out.read_text())
    old = json.loads(default_fits_path().read_text())
    assert new["model_sha256"] == old["model_sha256"]
    for name in MUSCLES:
        assert new["muscles"][name]["degree"] == old["muscles"][name]["degree"]
        np.testing.assert_allclose(
            new["muscles"][name]["coefficients"], old["muscles"][name]["coefficients"], atol=1e-9
        )


# -- fits whose lengths leave the spindle's range, field types, unreadable files -------------
def _write_doc(js: Path, edit) -> None:
    doc = json.loads(js.read_text())
    edit(doc)
    js.write_text(json.dumps(doc))


@pytest.mark.parametrize(
    ("muscle", "coefficients", "length", "deg"),
    [
        # the committed BRA curve lifted by 0.5 L0: its longest fibre, at 0 deg, is
        # 1.0939 + 0.5 L0 (the exact model's BRA is longest when the elbow is straight)
        ("BRA", lambda c: [c[0] + 0.5, *c[1:]], "1.594", "0 deg"),
        # TRImed lowered by 0.2 L0: shortest at 0 deg, 0.5793 - 0.2 L0
        ("TRImed", lambda c: [c[0] - 0.2, *c[1:]], "0.3793", "0 deg"),
        # 1.55 - 0.55 x^2 = 1.275 - 0.275 T2(x): both ends at 1.0 L0 (in range), 1.55 L0 at
        # mid-range (65 deg), where only an interior extremum reveals it
        ("BRA", lambda c: [1.275, 0.0, -0.275], "1.55", "65 deg"),
    ],
)
def test_fits_leaving_the_valid_length_range_are_refused(tmp_path, muscle, coefficients,
                                                         length, deg):
    _, js = _copy_fits(tmp_path)

    def edit(doc):
        entry = doc["muscles"][muscle]
        entry["coefficients"] = coefficients(entry["coefficients"])

    _write_doc(js, edit)
    with pytest.raises(LengthFitsError, match="valid range") as err:
        load_length_fits(js)
    message = str(err.value)
    assert muscle in message and f"{length} L0" in message and deg in message
    assert str(js) in message and REGENERATE_COMMAND in message


@pytest.mark.parametrize(
    "edit",
    [
        lambda doc: doc["muscles"]["BRA"].update(coefficients="123"),  # was read as (1, 2, 3)
        lambda doc: doc["muscles"]["BRA"].update(coefficients=[True, 0.1]),
        lambda doc: doc["muscles"]["BRA"].update(coefficients=[0.9, "0.1"]),
        lambda doc: doc["muscles"]["BRA"].update(coefficients={"0": 0.9}),
        lambda doc: doc["muscles"]["BRA"].update(coefficients=[10**400]),  # OverflowError
        lambda doc: doc["muscles"]["BRA"].update(max_error_L0="0.0003"),
        lambda doc: doc.update(valid_range_rad="02"),
        lambda doc: doc.update(valid_range_rad=[0.0, 1.0, 2.0]),
        lambda doc: doc.update(model_sha256=list(range(64))),
        lambda doc: doc.update(muscles=[["BRA", {}]]),
    ],
)
def test_fields_must_have_their_json_types(tmp_path, edit):
    _, js = _copy_fits(tmp_path)
    _write_doc(js, edit)
    with pytest.raises(LengthFitsError, match="malformed") as err:
        load_length_fits(js)
    assert REGENERATE_COMMAND in str(err.value)


@pytest.mark.parametrize("kind", ["directory", "not utf-8"])
def test_unreadable_file_raises_length_fits_error(tmp_path, kind):
    path = tmp_path / "length_fits.json"
    if kind == "directory":
        path.mkdir()
    else:
        path.write_bytes(b'{"format": "\xff\xfe proprio"}')
    with pytest.raises(LengthFitsError, match="cannot read") as err:
        load_length_fits(path)
    assert str(path) in str(err.value) and REGENERATE_COMMAND in str(err.value)


# -- an edited model gets its own fits -------------------------------------
BRA_P1 = '<site name="BRA-P1" pos="0.0068 -0.1739 -0.0036"/>'
ENV_IDS = ("proprio_env/ElbowReach-v0", "proprio_env/ProsthesisElbow-v0")
ANGLES_DEG = (5.0, 40.0, 80.0, 125.0)


def _edited_model(tmp_path: Path, dy_m: float) -> Path:
    """elbow.xml with BRA's origin (BRA-P1, on the humerus) moved by ``dy_m`` along y."""
    text = model_path().read_text()
    assert text.count(BRA_P1) == 1
    xml = tmp_path / f"elbow_bra_{dy_m:+.3f}.xml"
    xml.write_text(text.replace(BRA_P1, f'<site name="BRA-P1" pos="0.0068 {-0.1739 + dy_m:.4f} '
                                        '-0.0036"/>'))
    return xml


def _reset_lengths(env_id: str, angles_deg, **kwargs) -> np.ndarray:
    import gymnasium as gym

    import proprio_env  # noqa: F401  (registers the ids)

    env = gym.make(env_id, **kwargs)
    out = [env.reset(seed=0, options={"angle_deg": a})[1]["length_L0"] for a in angles_deg]
    env.close()
    return np.array(out)


@pytest.mark.parametrize("env_id", ENV_IDS)
@pytest.mark.parametrize(("source", "backend"),
                         [("reduced", "numpy"), ("encoder", "numpy"), ("reduced", "c")])
def test_edited_model_gets_its_own_fits(tmp_path, env_id, source, backend):
    from proprio_env.body.model import load_model
    from proprio_env.body.muscle_length import sweep

    xml = _edited_model(tmp_path, 0.025)  # BRA origin 2.5 cm further from the elbow
    angles = np.radians(ANGLES_DEG)
    exact = sweep(load_model(xml), angles).fibre_length_L0
    # the bundled fits are far off for this model: the test can tell the two apart
    assert np.max(np.abs(load_length_fits().length_L0(angles) - exact)) > 0.25
    lengths = _reset_lengths(env_id, ANGLES_DEG, xml_file=str(xml), afferent_source=source,
                             backend=backend)
    np.testing.assert_allclose(lengths, exact, rtol=0, atol=1e-3)  # the fits' 0.001 L0 target


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_bundled_model_and_its_copy_use_the_committed_fits(tmp_path, env_id):
    copy = tmp_path / "my_elbow.xml"
    shutil.copy(model_path(), copy)
    committed = load_length_fits().length_L0(np.radians(ANGLES_DEG))
    for xml in (None, str(copy)):
        lengths = _reset_lengths(env_id, ANGLES_DEG, xml_file=xml, afferent_source="reduced")
        np.testing.assert_array_equal(lengths, committed)


def test_edited_model_leaving_the_length_range_is_refused(tmp_path):
    import gymnasium as gym

    import proprio_env  # noqa: F401

    xml = _edited_model(tmp_path, -0.025)  # BRA origin 2.5 cm closer: 0.33 L0 at 130 deg
    with pytest.raises(LengthFitsError, match="valid range") as err:
        gym.make("proprio_env/ElbowReach-v0", xml_file=str(xml), afferent_source="reduced")
    message = str(err.value)
    assert str(xml) in message and "BRA" in message and "130 deg" in message
    named = float(re.search(r"length is ([0-9.]+) L0", message).group(1))
    assert abs(named - 0.32864) <= 1e-3  # the exact model's BRA length at 130 deg


def test_fits_path_is_checked_against_the_env_model(tmp_path):
    from proprio_env.body.length_fitting import fit_document, write_fits
    from proprio_env.body.model import load_model
    from spindle.chain import ChainConfig

    xml = _edited_model(tmp_path, 0.025)
    # the committed fits, passed explicitly, are stale for the edited model
    with pytest.raises(LengthFitsError, match="stale"):
        _reset_lengths(ENV_IDS[0], [60.0], xml_file=str(xml), afferent_source="reduced",
                       chain_config=ChainConfig(fits_path=default_fits_path()))
    # fits made for it with the script's code are used as given
    doc, _ = fit_document(load_model(xml), xml)
    js = tmp_path / "edited_fits.json"
    write_fits(doc, js)
    lengths = _reset_lengths(ENV_IDS[0], ANGLES_DEG, xml_file=str(xml),
                             afferent_source="reduced", chain_config=ChainConfig(fits_path=js))
    np.testing.assert_array_equal(lengths, load_length_fits(js, model_xml=xml).length_L0(
        np.radians(ANGLES_DEG)))


def test_fits_of_an_edited_model_are_made_once_per_process_by_its_sha256(tmp_path, monkeypatch):
    """docs/envs.md: a fit made on load, cached per process by the file's sha256. Counted:
    one fit per distinct file content, whatever the path, env id or number of envs; none for
    the bundled model or its byte-identical copy (the committed fits)."""
    import gymnasium as gym

    import proprio_env  # noqa: F401
    from proprio_env.body import length_fitting

    monkeypatch.setattr(length_fitting, "_FITTED", {})  # this test's own process cache
    fitted = []
    fit_document = length_fitting.fit_document

    def counting(model, path, *args, **kwargs):
        fitted.append(Path(path).name)
        return fit_document(model, path, *args, **kwargs)

    monkeypatch.setattr(length_fitting, "fit_document", counting)
    a = _edited_model(tmp_path, 0.025)
    (tmp_path / "elsewhere").mkdir()
    a_copy = tmp_path / "elsewhere" / "renamed.xml"
    shutil.copy(a, a_copy)
    b = _edited_model(tmp_path, 0.02)
    bundled_copy = tmp_path / "my_elbow.xml"
    shutil.copy(model_path(), bundled_copy)

    def make(env_id, xml):
        gym.make(env_id, xml_file=str(xml), afferent_source="reduced", backend="numpy").close()

    make(ENV_IDS[0], a)
    assert fitted == [a.name]
    for env_id in ENV_IDS:
        make(env_id, a)
        make(env_id, a_copy)  # the same bytes: the same fits, not fitted again
    assert fitted == [a.name]
    make(ENV_IDS[1], b)
    make(ENV_IDS[0], b)
    assert fitted == [a.name, b.name]
    make(ENV_IDS[0], bundled_copy)
    assert fitted == [a.name, b.name]  # the committed fits: loaded, not fitted
    assert len(length_fitting._FITTED) == 3

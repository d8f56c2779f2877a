"""Sim-to-real gap diagnosis.  Most tests use the analytic TOY backend (not physics:
it only exercises the gap logic); one runs real tiny-mesh FEM solves through the cache."""

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from elastimap.errors import UserError
from elastimap.gap import effects as fx
from elastimap.gap import measured, synth
from elastimap.gap.diagnose import diagnose
from elastimap.gap.settings import Settings
from elastimap.gap.simulate import Simulator

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def dhe():
    return synth.phantom_design(10, 0)


# ---------------------------------------------------------------- effects and format
def test_effect_spec_parsing_and_switches():
    ((e, m),) = fx.parse_spec("friction=0.3")
    assert e.name == "friction" and m == 0.3
    for bad in ("friction", "nope=1", "friction=x", "friction=0.1,friction=0.2", "skin=1000"):
        with pytest.raises(UserError):
            fx.parse_spec(bad)
    from elastimap.solver.params import SolveParams

    p = SolveParams()
    assert fx.get("friction").apply_params(p, 0.0) is p  # nominal = baseline
    assert fx.get("friction").apply_params(p, 0.5).disc.friction_kt == 0.5
    assert fx.get("skin").apply_params(p, 20.0).tissue.skin_thickness == fx.SKIN_THICKNESS
    assert fx.get("probe_moduli").apply_params(p, 2.0).probe.layers[0][1] == 600.0
    assert fx.get("offaxis").apply_params(p, 2.0).disc.symmetry == "full"
    from elastimap.camera.optics import SensorModel

    assert fx.get("saturation").apply_sensor(SensorModel(), 0.2).w_sat == 0.2
    assert "offaxis" not in fx.DEFAULT_CANDIDATES
    # the sensitivity magnitude lies in the grid's range, away from the nominal
    for e in fx.EFFECTS.values():
        assert e.lo <= e.sensitivity <= e.hi and not e.is_nominal(e.sensitivity), e.name
    assert fx.get("nonlinearity").sensitivity == 0.5 and fx.get("friction").sensitivity == fx.get("friction").hi


def test_phantom_design_is_valid_for_every_effect():
    from elastimap.gap.simulate import base_params

    for row in synth.phantom_design(30, 3):
        for e in fx.EFFECTS.values():
            for m in e.grid:
                e.apply_params(base_params("tiny", *row), m).validate()


def test_measured_roundtrip_and_validation(tmp_path, toy, dhe):
    meas, truth = synth.synthesize(dhe, [(fx.get("skin"), 30.0)], toy, frames=4, seed=1, force_noise=0.01)
    assert meas.synthetic and "SYNTHETIC" in meas.description and meas.has_force
    for fmt in ("csv", "parquet"):
        d = tmp_path / fmt
        tp = measured.write(meas, d, fmt)
        synth.seal(truth, d)
        back = measured.load(d)
        assert back.ids == meas.ids and np.allclose(back.y, meas.y) and np.allclose(back.se, meas.se)
        assert back.difference[0].shape == meas.difference[0].shape and back.synthetic
        assert np.allclose(back.force, meas.force) and np.allclose(
            back.difference_se[0], meas.difference_se[0], rtol=1e-6
        )
        assert any(p.name.startswith("synthetic_") for p in d.iterdir())
        assert synth.unseal(d)["effects"][0]["name"] == "skin"
        assert "skin" not in tp.read_text() if fmt == "csv" else True  # the label is not in the table
    d = tmp_path / "csv"
    df = pd.read_csv(d / "measured.csv")

    def bad(frame, word, sidecar=None):
        b = tmp_path / f"bad{abs(hash(word)) % 10000}"
        b.mkdir(exist_ok=True)
        frame.to_csv(b / "measured.csv", index=False)
        if sidecar is not None:
            (b / "measured.json").write_text(sidecar)
        with pytest.raises(UserError) as err:
            measured.load(b)
        assert word in str(err.value) and "\n" not in str(err.value)

    bad(df.drop(columns=["E"]), "missing column")
    bad(pd.concat([df, df.iloc[:1]]), "duplicate id")
    bad(df.assign(d=-1.0), "positive")
    bad(df.drop(columns=["O1"]), "O1,O2,O3")
    bad(df.assign(difference="nothere.npy"), "does not exist")
    bad(df.iloc[:3], "at least 4")
    bad(df, "not valid JSON", sidecar="{")
    bad(df, "not an elastimap", sidecar=json.dumps({"kind": "other"}))
    with pytest.raises(UserError, match="no such"):
        measured.load(tmp_path / "nowhere")


def test_simulator_cache_reuses_solves(tmp_path, dhe):
    from elastimap.gap.simulate import base_params

    ps = [base_params("tiny", *r) for r in dhe[:3]]
    a = Simulator(tmp_path, "tiny", "toy")
    ra = a.run(ps)
    assert a.stats["solved"] == 3
    b = Simulator(tmp_path, "tiny", "toy")
    rb = b.run(ps + ps[:1])
    assert b.stats["solved"] == 0 and b.stats["hits"] == 4
    assert np.array_equal(ra[0].image, rb[0].image) and rb[3].key == ra[0].key
    # the cache is a solve store: the same rows read through SolveStore, labelled SYNTHETIC,
    # and they never answer for the FEM
    from elastimap.dataset.store import SolveStore

    got = SolveStore(tmp_path, solver="synthetic").get(ps[1], need_raw=True)
    assert got is not None and np.array_equal(got.image, ra[1].image) and np.array_equal(got.image_raw, ra[1].image_raw)
    assert SolveStore(tmp_path).get(ps[1]) is None


# ---------------------------------------------------------------- diagnosis (TOY backend)
class MeshToy:
    """TOY stand-in for a discretised model (tests only, not physics): the toy backend's images
    and force carry an error that shrinks with the mesh size h0 like a converging FEM does
    (images ~ h0^3, force ~ h0), so two mesh levels disagree and data from a finer level differ
    from the diagnosis's model the way a re-implementation would."""

    H0 = {"tiny": 3.2, "coarse": 2.0, "default": 1.6, "fine": 1.1}

    def __init__(self, mesh, a=0.002, b=0.01):
        self.inner = Simulator(None, mesh, "toy")
        self.mesh, self.backend, self.stats = mesh, "toy", self.inner.stats
        self.f, self.g = 1 + a * self.H0[mesh] ** 3, 1 + b * self.H0[mesh]

    def run(self, plist):
        from elastimap.gap.simulate import Record

        out = []
        for r in self.inner.run(plist):
            bg = r.image_raw - r.image
            out.append(
                Record(
                    f"{r.key}@{self.mesh}",
                    r.O1 * self.f,
                    r.O2 * self.f,
                    r.O3,
                    r.force * self.g,
                    r.pixel,
                    r.image * self.f,
                    bg + r.image * self.f,
                    r.seconds,
                )
            )
        return out


SMALL = "friction,background_E,probe_E1,probe_E2,probe_moduli,saturation,blur,gamma,indentation"


def test_diagnosis_identifies_fits_and_shrinks(toy, dhe, tmp_path):
    meas, _ = synth.synthesize(dhe, [(fx.get("friction"), 0.6)], toy, frames=6, seed=2)
    res = diagnose(
        meas,
        fx.parse_list(SMALL),
        toy,
        Settings(inverse=True, n_train=30, train_repeats=2, train_epochs=150, bootstrap=50),
    )
    ev = res["evaluation"]
    assert ev["outcome"] == "explained" and ev["winner"] == "friction" and ev["views"] == ["profile"]
    top = ev["ranking"][0]
    assert top["magnitude"][0] == pytest.approx(0.6, rel=0.1)
    assert top["magnitude_ci"][0][0] <= top["magnitude"][0] <= top["magnitude_ci"][0][1]
    assert res["shrink_features"]["shrink"] > 0.7
    si = res["shrink_inverse"]
    assert si["mean_error_after"] < si["mean_error_before"]
    assert res["where"]["image"]["rings"] and "image_after" in res["where"]
    from elastimap.gap import report

    doc = report.write(res, tmp_path / "rep")
    md = (tmp_path / "rep" / "report.md").read_text()
    assert "SYNTHETIC" in md and "explained by friction" in md and "Every view" in md
    for f in doc["figures"]:
        assert (tmp_path / "rep" / f).stat().st_size > 1000
    assert "profile.png" in doc["figures"] and "residual_map.png" in doc["figures"]
    html = (tmp_path / "rep" / "report.html").read_text()
    assert html.startswith("<!DOCTYPE html>") and "data:image/png;base64," in html and "<table>" in html
    js = json.loads((tmp_path / "rep" / "diagnosis.json").read_text())
    assert js["summary"]["winner"] == "friction" and js["summary"]["model_error"] == "assumed"


def test_reimplementation_gives_no_gap_only_with_measured_model_error(dhe):
    """Data from a finer discretisation (no effect) than the diagnosis: no significant gap once the
    model error is measured from two mesh levels; the old assumed 0.5 % floor calls it significant."""
    data = MeshToy("default")
    meas, _ = synth.synthesize(dhe, [], data, frames=6, seed=3)
    sim, fine = MeshToy("tiny"), MeshToy("coarse")
    cands = fx.parse_list("friction,saturation")
    st = Settings(inverse=False, bootstrap=20)
    res = diagnose(meas, cands, sim, st, fine)
    assert res["model_error"]["kind"] == "measured"
    assert res["evaluation"]["outcome"] == "no significant gap", res["evaluation"]["reduced_chi2_baseline"]
    # the closed-world budget (no model-form level): the assumed floor calls it significant
    closed = Settings(inverse=False, bootstrap=20, model_form=False)
    assert diagnose(meas, cands, sim, closed)["evaluation"]["outcome"] != "no significant gap"
    # an effect on top of the same re-implementation is still found
    meas, _ = synth.synthesize(dhe, [(fx.get("friction"), 0.8)], data, frames=6, seed=4)
    ev = diagnose(meas, cands, sim, st, fine)["evaluation"]
    assert ev["significant"] and "friction" in ev["ambiguous_set"], ev["outcome"]


def test_no_gap_and_unexplained_outcomes(toy, dhe):
    st = Settings(inverse=False, bootstrap=20)
    clean, _ = synth.synthesize(dhe, [], toy, frames=6, seed=3)
    assert diagnose(clean, fx.parse_list("friction,skin"), toy, st)["evaluation"]["outcome"] == "no significant gap"
    meas, _ = synth.synthesize(dhe, [(fx.get("skin"), 40.0)], toy, frames=6, seed=4)
    ev = diagnose(meas, fx.parse_list("friction,saturation,vignetting"), toy, st)["evaluation"]
    assert ev["outcome"] == "unexplained" and ev["winner"] is None and ev["ambiguous_set"] == []


def test_ambiguity_reported_with_separating_measurement(toy, dhe):
    """In the TOY model only the first probe layer acts, so a softer layer 1 and a softer probe
    (all layers) are look-alikes: both are reported, with what would separate them."""
    meas, _ = synth.synthesize(dhe, [(fx.get("probe_E1"), 200.0)], toy, frames=6, seed=5)
    # the closed world (data from the same TOY): with the model-form level the TOY's probe_moduli
    # falls > 4.6 behind and the set is probe_E1 alone; the ambiguity mechanism is what this tests
    res = diagnose(
        meas,
        fx.parse_list("probe_E1,probe_moduli,friction,saturation"),
        toy,
        Settings(inverse=False, bootstrap=20, model_form=False),
    )
    ev = res["evaluation"]
    assert ev["outcome"] == "ambiguous" and set(ev["ambiguous_set"]) == {"probe_E1", "probe_moduli"}
    rows = {r["effect"]: r for r in ev["ranking"]}
    assert rows["probe_E1"]["magnitude_ci"][0][0] <= 200.0 <= rows["probe_E1"]["magnitude_ci"][0][1]
    p = res["proposal"]
    assert p["recommendation"]["measurement"] and len(p["phantoms"]) == 3
    (sep_force,) = p["force"].values()
    assert sep_force == pytest.approx(0.0, abs=1e-9)  # the TOY force ignores the probe
    assert p["second_depth"] and "solved_pair_separation" in p["phantoms"][0]
    from elastimap.gap import report

    assert "cannot be told apart" in report.verdict_line(res)


def test_family_composes_members_and_pays_for_its_parameters(toy, dhe):
    meas, _ = synth.synthesize(dhe, [(fx.get("probe_E1"), 220.0)], toy, frames=6, seed=6)
    ev = diagnose(
        meas, fx.parse_list("probe_E1,probe_E2,probe_E3,saturation"), toy, Settings(inverse=False, bootstrap=20)
    )["evaluation"]
    rows = {r["effect"]: r for r in ev["ranking"]}
    fam = rows["probe_layers_E"]
    assert fam["n_params"] == 3 and fam["members"] == ["probe_E1", "probe_E2", "probe_E3"]
    assert fam["magnitude"][0] == pytest.approx(220.0, rel=0.03)
    assert fam["score"] > rows["probe_E1"]["score"] and ev["winner"] == "probe_E1"


def test_frames_give_features_images_and_pixel_noise(tmp_path, toy, dhe):
    """Measured data given as frames keep the difference image (residual map) and its noise."""
    from elastimap.camera.frames import write_frames
    from elastimap.camera.optics import SensorModel, render_pair
    from elastimap.gap.simulate import base_params

    sensor = SensorModel()
    recs = toy.run([base_params("tiny", *r) for r in dhe[:4]])
    rows = []
    rng = np.random.default_rng(0)
    for i, r in enumerate(recs):
        L, B = render_pair(sensor, r.image_raw, r.image, r.pixel, 4, rng)
        li = write_frames(L, tmp_path, f"les{i}")
        bi = write_frames(B, tmp_path, f"bg{i}")
        rows.append(
            {
                "id": f"P{i}",
                "d": dhe[i, 0],
                "h": dhe[i, 1],
                "E": dhe[i, 2],
                "images": ";".join(Path(x).name for x in li),
                "background": ";".join(Path(x).name for x in bi),
            }
        )
    pd.DataFrame(rows).to_csv(tmp_path / "measured.csv", index=False)
    m = measured.load(tmp_path)
    assert m.has_images and all(s is not None and s.shape == m.difference[0].shape for s in m.difference_se)
    assert np.all(m.se > 0) and np.all(np.isfinite(m.y))


def test_profile_noise_is_calibrated(toy, dhe):
    """Noise-only data: χ²/N of the profile and features with the frame-scatter errors is about 1."""
    from elastimap.gap.measured import measured_views
    from elastimap.gap.simulate import base_params
    from elastimap.gap.views import sim_views

    recs = toy.run([base_params("tiny", *r) for r in dhe])
    zs = {"features": [], "profile": []}
    for seed in range(3):
        meas, _ = synth.synthesize(dhe, [], toy, frames=8, seed=10 + seed)
        mv = measured_views(meas, meas.sensor_model(), meas.settings())
        V0, _ = sim_views(recs, meas.sensor_model(), meas.settings())
        for k in zs:
            zs[k].append(((mv[k][0] - V0[k]) / mv[k][1]) ** 2)
    for k, z in zs.items():
        assert 0.3 < np.mean(z) < 2.0, (k, np.mean(z))


def test_tiny_blind_benchmark_with_model_form_error(dhe):
    from elastimap.gap import selftest

    cands = fx.parse_list("friction,background_E,saturation,blur")
    outside = fx.parse_list("aspect,stray_light")
    res = selftest.run(
        4,
        MeshToy("tiny"),
        MeshToy("default"),
        cands,
        outside,
        MeshToy("coarse"),
        n_phantoms=10,
        frames=6,
        seed=5,
        st=Settings(inverse=False, bootstrap=20),
        log=None,
    )
    assert [r["kind"] for r in res["trials"]] == ["none", "in", "out", "in"]
    assert res["no_effect_no_gap_rate"] == 1.0
    assert res["in_library_set_holds_truth_rate"] >= 0.5
    assert res["out_of_library_confident_wrong_rate"] <= 1.0
    assert sum(sum(r.values()) for r in res["confusion"].values()) == 4
    md = selftest.markdown(res)
    assert "SYNTHETIC" in md and "Confusion matrix" in md and "data from mesh `default`" in md
    with pytest.raises(ValueError):
        selftest.run(1, MeshToy("tiny"), MeshToy("default"), cands, cands[:1], log=None)


def test_blind_benchmark_tries_every_outside_effect_and_keeps_the_phantoms(dhe):
    """Out-of-library trials take the outside effects in turn (each one tried), and a new trial
    seed with a fixed phantom seed draws new trials on the same phantoms."""
    from elastimap.gap import selftest

    cands = fx.parse_list("friction,background_E")
    outside = fx.parse_list("aspect,stray_light")
    kw = dict(n_phantoms=6, frames=4, st=Settings(inverse=False, bootstrap=10), log=None)
    a = selftest.run(7, MeshToy("tiny"), MeshToy("default"), cands, outside, seed=1, phantom_seed=0, **kw)
    assert sorted(r["true_effect"] for r in a["trials"] if r["kind"] == "out") == ["aspect", "stray_light"]
    assert a["phantom_seed"] == 0 and a["seed"] == 1
    assert "phantoms: seed 0" in selftest.markdown(a)


class RemeshToy(MeshToy):
    """MeshToy whose discretisation error also depends on the geometry (tests only, not physics):
    a skin layer (another mesh) makes it 1 + ``geom`` times larger, so the baseline's error does
    not carry over to the skin candidate -- as on the FEM's coarse mesh between slab thicknesses."""

    def __init__(self, mesh, a=0.002, geom=3.0):
        super().__init__(mesh, a=a)
        self.a, self.geom = a, geom

    def run(self, plist):
        out = []
        for p in plist:
            self.f = 1 + self.a * self.H0[self.mesh] ** 3 * (1 + (self.geom if p.tissue.skin_thickness > 0 else 0.0))
            out += super().run([p])
        return out


def test_remeshing_effect_gets_its_own_model_error(dhe, monkeypatch):
    """A remeshing candidate is extrapolated with its own two mesh levels at its refined
    magnitudes: the right effect, near the truth.  Carrying the baseline's error over to it
    instead (the effect marked as not remeshing) leaves it unexplained.
    (Its interval here misses the truth by 1-2 widths: the emulator between the nominal and the
    one refined magnitude, 5 and ~47 kPa, is not measured at 40; docs/gap.md.)"""
    data = RemeshToy("default")
    meas, _ = synth.synthesize(dhe, [(fx.get("skin"), 40.0)], data, frames=6, seed=7)
    cands = fx.parse_list("skin,friction,saturation")
    # the closed world (data from the same TOY at another mesh level): no model-form level, so the
    # mesh error alone decides (with the level's slack both ways explain it); single effects only:
    # without its own error skin fails, and a pair (skin + saturation) then makes up for the missing
    # error -- what this test isolates is the own error, not the pairs
    st = Settings(inverse=False, bootstrap=20, model_form=False, pair_top=0)
    ev = diagnose(meas, cands, RemeshToy("tiny"), st, RemeshToy("coarse"))["evaluation"]
    top = {r["effect"]: r for r in ev["ranking"]}["skin"]
    assert ev["outcome"] == "explained" and ev["winner"] == "skin", ev["outcome"]
    assert top["own_model_error_at"]["skin"], top["own_model_error_at"]
    assert abs(top["magnitude"][0] - 40.0) < 0.2 * (40.0 - 5.0), top["magnitude"]
    monkeypatch.setattr(fx, "OWN_ERROR", frozenset())
    ev = diagnose(meas, cands, RemeshToy("tiny"), st, RemeshToy("coarse"))["evaluation"]
    top = {r["effect"]: r for r in ev["ranking"]}["skin"]
    assert not top["own_model_error_at"]
    assert ev["outcome"] != "explained", (ev["outcome"], top["magnitude"])


def test_camera_effects_are_extrapolated_through_their_own_camera(dhe, monkeypatch):
    """An optics candidate costs no solves, so it is rendered from both mesh levels' baseline
    records through its own camera and extrapolated with its own Δ; the baseline's correction,
    made through the nominal camera, is not the correction through a saturating one.  Data from
    a finer TOY level with a strong saturation: the own correction fits better (held-out χ²),
    the candidate carries its own Δ into its interval, and the interval holds the truth."""
    from elastimap.gap import adaptive, model_error

    data = MeshToy("default", a=0.01)
    meas, _ = synth.synthesize(dhe, [(fx.get("saturation"), 0.2)], data, frames=6, seed=5)
    cands = fx.parse_list("saturation,friction,gamma")
    st = Settings(inverse=False, bootstrap=20)
    ev = diagnose(meas, cands, MeshToy("tiny", a=0.01), st, MeshToy("coarse", a=0.01))["evaluation"]
    row = {r["effect"]: r for r in ev["ranking"]}["saturation"]
    assert ev["winner"] == "saturation", ev["outcome"]
    assert row["_model"].own_delta(row["_theta"]) is not None
    lo, hi = row["magnitude_ci"][0]
    assert lo <= 0.2 <= hi, (row["magnitude"], row["magnitude_ci"])

    def baseline_only(c, me):
        c.V, c.D = model_error.correct(c.V, c.D, me)

    monkeypatch.setattr(model_error, "own_correct_rendered", baseline_only)
    monkeypatch.setattr(adaptive, "RENDER_TOL", 10.0)  # no exact renders either: the old path
    ev0 = diagnose(meas, cands, MeshToy("tiny", a=0.01), st, MeshToy("coarse", a=0.01))["evaluation"]
    row0 = {r["effect"]: r for r in ev0["ranking"]}["saturation"]
    assert row0["_model"].own_delta(row0["_theta"]) is None
    assert row["ssr_cv"] < row0["ssr_cv"], (row["ssr_cv"], row0["ssr_cv"])


def test_an_effect_beyond_its_grid_extends_the_range_within_its_physical_limits(dhe):
    """Real effects need not stay on the grid: a fit at the grid's end moves that end out
    (half the grid's width a refinement round, held inside the effect's physical limits).  TOY
    data with a saturation of 0.1 mm, below the grid's 0.15 mm: the range is extended, the fit
    leaves the end and its interval holds the truth; without the extension it sticks at 0.15."""
    e = fx.get("saturation")
    assert e.beyond(0.15, 0.15, 0.7) == pytest.approx(0.05)  # 0.15 - 0.275, held at the limit 0.05
    assert e.beyond(0.7, 0.15, 0.7) == pytest.approx(0.975)
    assert e.beyond(0.4, 0.15, 0.7) is None  # inside the range
    assert fx.get("nonlinearity").beyond(1.0, 0.0, 1.0) is None  # β = 1 is the physical end
    assert fx.get("tissue_nu").beyond(0.495, 0.45, 0.495) == pytest.approx(0.499)
    assert fx.get("friction").beyond(0.0, 0.0, 1.0) is None  # 0 = frictionless, the end

    data = MeshToy("default", a=0.002)
    meas, _ = synth.synthesize(dhe, [(e, 0.1)], data, frames=6, seed=4)
    cands = fx.parse_list("saturation,friction,gamma")
    st = Settings(inverse=False, bootstrap=20, model_form=False)  # closed world: the same TOY's mesh levels
    ev = diagnose(meas, cands, MeshToy("tiny", a=0.002), st, MeshToy("coarse", a=0.002))["evaluation"]
    row = {r["effect"]: r for r in ev["ranking"]}["saturation"]
    assert row["extended_to"].get("saturation"), row.get("extended_to")
    assert not row["at_grid_edge"], row["magnitude"]
    lo, hi = row["magnitude_ci"][0]
    assert lo <= 0.1 <= hi, (row["magnitude"], row["magnitude_ci"])

    class NoBeyond(fx.Effect):
        def beyond(self, m, lo, hi, step=0.5):
            return None

    stuck = NoBeyond(**{f.name: getattr(e, f.name) for f in dataclasses.fields(e)})
    ev0 = diagnose(meas, [stuck, *cands[1:]], MeshToy("tiny", a=0.002), st, MeshToy("coarse", a=0.002))
    row0 = {r["effect"]: r for r in ev0["evaluation"]["ranking"]}["saturation"]
    assert row0["at_grid_edge"] and row0["magnitude"][0] == pytest.approx(0.15), row0["magnitude"]


def test_a_family_holds_its_members_inside_their_grids():
    """A member's range extended for its own single fit is not the family's: with several
    parameters beyond their grids a family mimics effects outside the library.  Plain arrays:
    each member's view is linear in its magnitude; the data ask for probe_E1 = 120 kPa (below
    its grid's 180) and probe_E2 = 160 kPa.  The single fit follows E1 onto the extended point;
    the family holds E1 at its grid's end 180, says so, and its interval stays inside the grid."""
    from elastimap.gap.candidates import Candidate
    from elastimap.gap.fit_models import Composed, Single

    names = ["features"]
    y0 = np.array([[1.0, 2.0, 3.0]])  # one phantom, three quantities
    slope = {"probe_E1": np.array([1.0, 0.0, 0.5]), "probe_E2": np.array([0.0, 1.0, -0.5]), "probe_E3": np.zeros(3)}

    def cand(name, extra=()):
        e = fx.get(name)
        g = np.array(sorted([*e.grid, *extra]))
        V = {"features": np.stack([y0 + 0.01 * (m - e.nominal) * slope[name] for m in g])}
        return Candidate(e, g, V, None, extended=list(extra))

    e1 = cand("probe_E1", extra=(90.0,))  # E1's own range extended to 90 kPa
    ms = [Single(cand(n) if n != "probe_E1" else e1, names) for n in ("probe_E1", "probe_E2", "probe_E3")]
    truth = {"probe_E1": 120.0, "probe_E2": 160.0}
    y = y0 + sum(0.01 * (v - fx.get(n).nominal) * slope[n] for n, v in truth.items())
    S, idx = np.full_like(y, 1e-3), np.arange(1)  # idx: the phantoms fitted
    assert ms[0].fit(y - 0.01 * (160.0 - 150.0) * slope["probe_E2"], S, idx)[0] == pytest.approx(120.0, abs=0.5)
    fam = Composed(fx.FAMILIES["probe_layers_E"], ms, y0, {"features": y0})
    th = fam.fit(y, S, idx)
    assert th[0] == pytest.approx(180.0), th  # held at its grid's end, not at the extended 120
    assert fam.at_edge(th)
    assert all(
        a >= fx.get(n).lo - 1e-9 and b <= fx.get(n).hi + 1e-9 for (a, b), n in zip(fam.interval(y, S, th), fam.labels)
    )


def test_profile_correction_stays_bounded_where_an_annulus_crosses_zero():
    """The Richardson correction of a candidate's profile is the baseline's scaled by the
    candidate's size (per phantom), exact for an effect that scales the image; a per-annulus
    ratio would blow up at the annulus where the baseline crosses zero."""
    from elastimap.gap.model_error import correct, profile_scale

    y0 = np.array([[1.0, 0.6, 0.2, 1e-6], [2.0, 1.0, 0.1, -1e-7]])
    delta = np.array([[0.01, 0.008, 0.004, 0.002], [0.02, 0.01, 0.002, 0.001]])
    me = {
        "_factor": {"features": np.ones((2, 3))},
        "_dprofile": 2.0 * delta,
        "_profile0": y0,
        "_dD": np.zeros((2, 4, 4)),
    }
    assert np.allclose(profile_scale(0.8 * y0, y0), 0.8)
    V = {"features": np.ones((2, 3)), "profile": 0.8 * y0}
    out, D = correct(V, np.zeros((2, 4, 4)), me)
    assert np.allclose(out["profile"], 0.8 * (y0 - 2.0 * delta))  # exact for a uniform scaling
    K = {"features": np.ones((3, 2, 3)), "profile": np.stack([0.5 * y0, y0, 1.5 * y0])}  # a sweep (K, n, q)
    out, _ = correct(K, None, me)
    assert np.allclose(out["profile"][2], 1.5 * (y0 - 2.0 * delta))


# ---------------------------------------------------------------- real FEM solves (tiny mesh)
def test_fem_backend_small_diagnosis(tmp_path):
    """4 phantoms, a 2-point friction sweep and an optics candidate, real tiny-mesh solves."""
    sim = Simulator(tmp_path / "cache", "tiny", "fem")
    fr = dataclasses.replace(fx.get("friction"), grid=(0.0, 0.3))
    dhe = np.array([[8.0, 8.0, 80.0], [6.0, 7.0, 50.0], [10.0, 10.0, 120.0], [7.0, 11.0, 60.0]])
    meas, _ = synth.synthesize(dhe, [(fr, 0.3)], sim, frames=4, seed=0)
    n_true = sim.stats["solved"]
    res = diagnose(meas, [fr, fx.get("saturation")], sim, Settings(inverse=False, bootstrap=20))
    ev = res["evaluation"]
    assert ev["best"] == "friction" and ev["ranking"][0]["magnitude"][0] == pytest.approx(0.3, rel=0.05)
    assert sim.stats["solved"] == n_true + 4  # only the baseline was new: friction=0.3 came from the cache


# ---------------------------------------------------------------- CLI
def test_cli_end_to_end_and_errors(tmp_path):
    py = [sys.executable, "-m", "elastimap.gap.cli"]
    m = tmp_path / "m"
    r = subprocess.run(
        py
        + [
            "synth",
            "--out",
            str(m),
            "--effect",
            "saturation=0.2",
            "--backend",
            "toy",
            "--mesh",
            "tiny",
            "--n",
            "8",
            "--cache",
            "none",
            "--no-progress",
        ],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert r.returncode == 0, r.stderr
    assert "SYNTHETIC" in r.stdout
    out = tmp_path / "d"
    r = subprocess.run(
        py
        + [
            "diagnose",
            "--measured",
            str(m),
            "--out",
            str(out),
            "--backend",
            "toy",
            "--cache",
            "none",
            "--effects",
            "saturation,friction,blur",
            "--no-inverse",
            "--no-progress",
            "--json",
        ],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["winner"] == "saturation"
    assert (out / "report.md").exists() and (out / "candidates.png").exists() and (out / "report.html").exists()
    for args, word in (
        (["diagnose", "--measured", str(tmp_path / "none"), "--out", str(out)], "no such"),
        (["synth", "--out", str(tmp_path / "m2"), "--effect", "bogus=1"], "unknown effect"),
        (["synth", "--out", str(m), "--effect", "friction=0.3"], "--overwrite"),
        (["diagnose", "--measured", str(m), "--out", str(out), "--effects", "x"], "unknown effect"),
        (["diagnose", "--measured", str(m), "--out", str(out), "--alpha", "2"], "alpha"),
        (
            ["diagnose", "--measured", str(m), "--out", str(out), "--error-mesh", "huge", "--backend", "toy"],
            "error-mesh",
        ),
        (["selftest", "--outside", "friction", "--effects", "friction", "--backend", "toy"], "outside"),
    ):
        r = subprocess.run(py + args, capture_output=True, text=True, cwd=ROOT)
        assert r.returncode == 2 and word in r.stderr and r.stderr.count("\n") == 1, r.stderr


def test_family_isolates_a_member_only_when_the_others_hold_their_nominal():
    from elastimap.gap.selftest import family_isolates

    row = {
        "members": ["probe_E1", "probe_E2", "probe_E3"],
        "nominal": [300.0, 150.0, 50.0],
        "magnitude_ci": [[192.8, 205.3], [145.2, 151.3], [48.7, 50.3]],
    }
    assert family_isolates(row, "probe_E1")
    assert not family_isolates(row, "probe_E2")  # E2's interval holds its nominal
    row["magnitude_ci"][2] = [45.0, 48.0]  # E3 off too: the family names two members
    assert not family_isolates(row, "probe_E1")
    assert not family_isolates({"members": ["friction"], "nominal": [0.0], "magnitude_ci": [[0.5, 0.7]]}, "friction")


def layers_E_row(magnitude, ci) -> dict:
    """A ranking row of the probe_layers_E family (fabricated: tests the reporting rules only)."""
    return {
        "effect": "probe_layers_E",
        "members": ["probe_E1", "probe_E2", "probe_E3"],
        "nominal": [300.0, 150.0, 50.0],
        "units": ["kPa"] * 3,
        "magnitude": list(magnitude),
        "magnitude_ci": [list(x) for x in ci],
    }


def test_a_family_that_isolates_one_member_is_reported_as_that_member():
    """The nested-model rule: a family in the reported set whose fit moves one member only is
    reported as that member, with the family's fitted magnitude; a family with two members off
    stays itself; a name reached twice keeps its better-scored entry."""
    from elastimap.gap.selection import reported_set

    fam = layers_E_row([199.0, 148.0, 49.5], [[192.8, 205.3], [145.2, 151.3], [48.7, 50.3]])
    single = {
        "effect": "probe_E1",
        "members": ["probe_E1"],
        "nominal": [300.0],
        "units": ["kPa"],
        "magnitude": [203.0],
        "magnitude_ci": [[190.0, 215.0]],
    }
    rep = reported_set([fam, single])
    assert list(rep) == ["probe_E1"]
    assert rep["probe_E1"]["via"] == "probe_layers_E" and rep["probe_E1"]["magnitude"] == [199.0]
    assert rep["probe_E1"]["magnitude_ci"] == [[192.8, 205.3]] and rep["probe_E1"]["_row"] is fam
    assert list(reported_set([single, fam])) == ["probe_E1"] and reported_set([single, fam])["probe_E1"]["via"] is None
    fam2 = dict(fam, magnitude_ci=[[192.8, 205.3], [145.2, 151.3], [45.0, 48.0]])
    assert list(reported_set([fam2, single])) == ["probe_layers_E", "probe_E1"]


def test_a_family_off_by_one_common_factor_is_reported_as_its_nested_effect():
    """probe_moduli (every layer modulus times one factor) is nested in probe_layers_E: a family
    fit whose members' intervals, as ratios to their nominals, share a part that excludes 1 is
    reported as probe_moduli with probe_moduli's own fit; members off by different factors, or
    a common part that holds 1, stay the family."""
    from elastimap.gap.selection import common_factor, reported_set
    from elastimap.gap.selftest import family_isolates

    # ratios [0.63, 0.70], [0.64, 0.70], [0.62, 0.71]: common part [0.64, 0.70]
    fam = layers_E_row([199.0, 101.0, 33.5], [[189.0, 210.0], [96.0, 105.0], [31.0, 35.5]])
    name, (lo, hi) = common_factor(fam)
    assert name == "probe_moduli" and lo == pytest.approx(0.64) and hi == pytest.approx(0.70)
    assert family_isolates(fam, "probe_moduli") and not family_isolates(fam, "probe_E1")
    own = {
        "effect": "probe_moduli",
        "members": ["probe_moduli"],
        "nominal": [1.0],
        "units": ["-"],
        "magnitude": [0.659],
        "magnitude_ci": [[0.652, 0.666]],
    }
    rep = reported_set([fam], [fam, own])
    assert list(rep) == ["probe_moduli"] and rep["probe_moduli"]["via"] == "probe_layers_E"
    assert rep["probe_moduli"]["magnitude"] == [0.659] and rep["probe_moduli"]["magnitude_ci"] == [[0.652, 0.666]]
    assert rep["probe_moduli"]["via_kind"] == "common factor"
    # without the nested effect among the candidates: the members' geometric-mean ratio
    rep = reported_set([fam])
    g = float(np.exp(np.mean(np.log([199.0 / 300, 101.0 / 150, 33.5 / 50]))))
    assert rep["probe_moduli"]["magnitude"][0] == pytest.approx(g)
    assert rep["probe_moduli"]["magnitude_ci"] == [[pytest.approx(0.64), pytest.approx(0.70)]]
    # different factors (E3 at 0.9-0.95): no common part
    assert common_factor(dict(fam, magnitude_ci=[[189.0, 210.0], [96.0, 105.0], [45.0, 47.5]])) is None
    # a common part that holds 1: not every member is off
    assert common_factor(dict(fam, magnitude_ci=[[189.0, 310.0], [96.0, 155.0], [31.0, 52.0]])) is None
    assert common_factor(dict(fam, effect="probe_layers_t", members=["probe_t1", "probe_t2", "probe_t3"])) is None


def test_the_jackknife_interval_matches_a_direct_computation():
    """The grouped jackknife interval over the held-out fits, against the textbook formula
    written out here, and clipped to the effect's range."""
    from scipy import stats as st

    from elastimap.gap.fit_models import jackknife_interval

    class M:
        def grid_of(self, l):
            return np.array([0.0, 10.0])

    rng = np.random.default_rng(3)
    folds = 5.0 + 0.1 * rng.standard_normal((12, 1))
    g = 12
    mean = folds[:, 0].mean()
    se = np.sqrt((g - 1) / g * sum((x - mean) ** 2 for x in folds[:, 0]))
    ((lo, hi),) = jackknife_interval(M(), np.array([5.02]), folds)
    assert lo == pytest.approx(5.02 - st.t.ppf(0.975, 11) * se) and hi == pytest.approx(5.02 + st.t.ppf(0.975, 11) * se)
    assert jackknife_interval(M(), np.array([9.9]), 9.9 + 0.5 * rng.standard_normal((12, 1)))[0][1] == 10.0
    assert jackknife_interval(M(), np.array([5.0]), folds[:2]) is None
    fam = jackknife_interval(
        type("F", (), {"grid_of": lambda self, l: np.array([-100.0, 100.0])})(),
        np.zeros(2),
        rng.standard_normal((10, 2)),
    )
    assert len(fam) == 2 and all(a < 0 < b for a, b in fam)


def test_a_fit_beyond_the_solved_magnitudes_counts_as_extrapolated():
    """Refinement also takes the best rows whose fit lies beyond their solved magnitudes (their
    score there is the end secant's guess): the rule that finds them."""
    from elastimap.gap.adaptive import extrapolated
    from elastimap.gap.candidates import Candidate

    e = fx.get("probe_moduli")  # nominal 1, range [0.6, 1.5], solved first at 1 and 1.5
    c = Candidate(e, np.array([1.0, 1.5]), {}, None, adaptive=True)
    byname = {"probe_moduli": c}
    assert extrapolated({"members": ["probe_moduli"], "magnitude": [0.74]}, byname, 0.03)
    assert not extrapolated({"members": ["probe_moduli"], "magnitude": [1.2]}, byname, 0.03)
    assert not extrapolated({"members": ["probe_moduli"], "magnitude": [0.98]}, byname, 0.03)  # within tol
    c.grid = np.array([0.74, 1.0, 1.5])
    assert not extrapolated({"members": ["probe_moduli"], "magnitude": [0.74]}, byname, 0.03)
    full = Candidate(fx.get("saturation"), np.array([0.15, 0.5, 0.7]), {}, None, adaptive=False)
    assert not extrapolated({"members": ["saturation"], "magnitude": [0.2]}, {"saturation": full}, 0.03)

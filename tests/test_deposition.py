"""Deposit analysis (CN, q6, solid-like, profiles), views, and the deposition / Hamaker / EPD-order studies."""
import json
import math

import numpy as np
import pytest

from sim.analysis import (coordination_numbers, deposited_mask, height_profile, packing_fraction, solid_like,
                          steinhardt_q6)


def _lattice(kind, n=5, a=1.0):
    basis = {"fcc": [[0, 0, 0], [.5, .5, 0], [.5, 0, .5], [0, .5, .5]], "bcc": [[0, 0, 0], [.5, .5, .5]],
             "sc": [[0, 0, 0]]}[kind]
    g = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3)
    return ((g[:, None, :] + np.array(basis)[None]) * a).reshape(-1, 3), n * a


@pytest.mark.parametrize("kind,rc,cn,q6", [("fcc", 0.8, 12, 0.57452), ("sc", 1.1, 6, 0.35355),
                                           ("bcc", 0.9, 8, 0.62854)])
def test_crystal_cn_and_q6(kind, rc, cn, q6):
    p, L = _lattice(kind)
    box = dict(length=[L] * 3, periodic=[1, 1, 1])
    assert np.all(coordination_numbers(p, None, r_cn=rc, **box) == cn)
    q = steinhardt_q6(p, r_cut=rc, **box)
    np.testing.assert_allclose(q, q6, atol=1e-4)


def test_q6_rotation_invariant_and_solid_like():
    p, L = _lattice("fcc", 4)
    rng = np.random.default_rng(0)
    # random rotation of a free fcc cluster: q6 of the interior is unchanged
    A = np.linalg.qr(rng.standard_normal((3, 3)))[0]
    c = p - p.mean(0)
    q0 = steinhardt_q6(c, r_cut=0.8)
    q1 = steinhardt_q6(c @ A.T, r_cut=0.8)
    np.testing.assert_allclose(q0, q1, atol=1e-10)
    solid, _ = solid_like(p, r_cut=0.8, length=[L] * 3, periodic=[1, 1, 1])
    assert solid.all()
    gas = rng.random((1500, 3)) * 10
    s_gas, _ = solid_like(gas, r_cut=1.3, length=[10] * 3, periodic=[1, 1, 1])
    assert s_gas.mean() < 0.02


def test_cn_uses_radii_and_periodic_images():
    pos = np.array([[0.05, 0.5, 0.5], [0.95, 0.5, 0.5], [0.5, 0.5, 0.5]])
    rad = np.array([0.05, 0.05, 0.1])
    assert list(coordination_numbers(pos, rad)) == [0, 0, 0]
    assert list(coordination_numbers(pos, rad, length=[1, 1, 1], periodic=[1, 0, 0])) == [1, 1, 0]


def test_height_profile_and_packing_fraction_exact_for_a_layer():
    # square monolayer of spheres touching the substrate: solid fraction of the slab [0, 2R] is pi/6
    R = 0.5
    g = np.stack(np.meshgrid(np.arange(10), np.arange(10), indexing="ij"), -1).reshape(-1, 2) * 2 * R + R
    pos = np.column_stack([g, np.full(len(g), R)])
    area = (20 * R) ** 2
    assert math.isclose(packing_fraction(pos, np.full(100, R), area, 0, 2 * R), math.pi / 6, rel_tol=1e-12)
    z, phi = height_profile(pos, np.full(100, R), area, bins=20)
    assert math.isclose(np.sum(phi) * (z[1] - z[0]), math.pi / 6 * 2 * R, rel_tol=1e-12)
    assert phi[10] > phi[0]  # widest at the centre plane


def test_deposited_mask_follows_contact_chains():
    R = 0.05
    pos = np.array([[0, 0, R], [0, 0, 3 * R], [0, 0, 5.02 * R], [1, 1, 0.5]])
    assert list(deposited_mask(pos, np.full(4, R))) == [True, True, True, False]


def test_extxyz_is_readable(tmp_path):
    from sim.views import write_extxyz

    frames = [{"t": 0.1 * k, "pos": np.random.default_rng(k).random((5, 3)), "radius": np.full(5, 0.05),
               "cn": np.arange(5)} for k in range(3)]
    path = write_extxyz(tmp_path / "x.extxyz", frames, box=[1, 2, 3], periodic=(True, True, False),
                        extra_names=("cn",))
    lines = path.read_text().splitlines()
    assert lines[0] == "5" and len(lines) == 3 * 7
    assert 'Lattice="1 0 0 0 2 0 0 0 3"' in lines[1] and 'pbc="T T F"' in lines[1]
    assert "Properties=species:S:1:pos:R:3:radius:R:1:cn:I:1" in lines[1]
    f = lines[2].split()
    assert f[0] == "P" and len(f) == 6 and f[-1] == "0"


@pytest.mark.slow
def test_hamaker_slope_within_5_percent():
    from sim.studies.hamaker import DEFAULTS, run_case

    r = run_case(dict(DEFAULTS, field=1e4, n_particles=30000, seed=3, area=1e-9))
    assert r["rel_err"] < 0.05, r
    assert r["n_deposited"] > 10000


def test_deposition_study_quick(tmp_path):
    from ptrack.cli import main

    js = tmp_path / "d.json"
    rc = main(["study", "deposition", "--example", "2", "--quick", "--out", str(tmp_path / "o"), "--json", str(js),
               "--quiet"])
    assert rc == 0
    d = json.loads(js.read_text())
    for k in ("n_particles", "steps", "wall_time_s", "mean_cn_final", "max_overlap_ratio"):
        assert k in d
    assert d["n_particles"] == 200 and d["steps"] == 100000
    assert 3.0 < d["mean_cn_final"] < 12.0  # a multilayer deposit has formed
    assert d["max_overlap_ratio"] < 0.2
    for f in ("snapshots.png", "final_deposit.png", "coordination_vs_time.png", "deposit.extxyz"):
        assert (tmp_path / "o" / f).stat().st_size > 1000


def test_epd_order_mobile_substrate_crystallises_sticking_one_does_not():
    from sim.studies.epd_order import DEFAULTS, run_case

    stick = run_case(dict(DEFAULTS, pe=50.0, a_over_lambda=5.0, n_particles=200, seed=1, substrate="stick"))
    mobile = run_case(dict(DEFAULTS, pe=50.0, a_over_lambda=5.0, n_particles=200, seed=1, substrate="contact"))
    for r in (stick, mobile):
        assert r["stuck_on_substrate"] > 20
        # every particle arrived: the deposit is a few layers thick, not the initial dilute cloud
        assert r["deposit_height"] < 0.5 * r["height"]
    # random sticking freezes a disordered first layer; a mobile substrate lets the deposit order
    assert stick["solid_fraction"] < 0.15
    assert mobile["solid_fraction"] > 0.3
    assert mobile["q6_mean"] > stick["q6_mean"]


def test_study_rejects_bad_option(capsys):
    from ptrack.cli import main

    assert main(["study", "deposition", "--example", "1", "--cn-factor", "0.5", "--quick"]) == 2
    assert "cn-factor" in capsys.readouterr().err


def test_epd_order_resumed_case_equals_uninterrupted(monkeypatch):
    import sim.studies.epd_order as eo

    monkeypatch.setattr(eo, "CHUNK_STEPS", 1000)
    case = dict(eo.DEFAULTS, pe=180.0, a_over_lambda=5.0, n_particles=60, seed=7, rep=0, substrate="contact")
    states = []
    full = eo.run_case(case, checkpoint=lambda s: states.append(s.get_state()) if not states else None)
    assert int(states[0]["step"]) == 1000 and full["steps"] > 2000
    assert eo.run_case(case, state=states[0]) == full  # bit-identical continuation from the checkpoint


def test_epd_order_case_files_are_skipped_on_rerun_and_checked(tmp_path, monkeypatch):
    import sim.studies.epd_order as eo
    from ptrack.errors import UserError

    calls = []

    def fake(case, checkpoint=None, state=None, progress=None):
        calls.append(case["seed"])
        return {"pe": case["pe"], "a_over_lambda": case["a_over_lambda"], "n_particles": case["n_particles"],
                "steps": 1, "solid_fraction": 0.5, "solid_fraction_interior": 0.5, "q6_mean": 0.4}

    monkeypatch.setattr(eo, "run_case", fake)
    case = dict(eo.DEFAULTS, pe=60.0, a_over_lambda=5.0, n_particles=100, seed=3, rep=0, substrate="contact")
    r1 = eo.run_case_in(case, tmp_path)
    r2 = eo.run_case_in(case, tmp_path)
    assert calls == [3] and r1 == r2  # the finished case is read back, not run again
    assert not list(tmp_path.glob("*.lock")) and len(eo.collect(tmp_path)) == 1
    with pytest.raises(UserError, match="another case"):
        eo.run_case_in(dict(case, seed=4), tmp_path)


def test_epd_order_trend_test_finds_a_known_slope_and_no_slope():
    import pandas as pd

    from sim.studies.epd_order import summarise

    rng = np.random.default_rng(0)
    pe = np.repeat([20.0, 60.0, 180.0, 540.0], 3)
    noise = 0.01 * rng.standard_normal(len(pe))
    rows = dict(pe=np.r_[pe, pe], a_over_lambda=np.r_[np.full(12, 5.0), np.full(12, 10.0)],
                solid_fraction=np.r_[0.8 - 0.2 * np.log10(pe) + noise, 0.5 + noise],
                n_particles=100, steps=1, q6_mean=0.4)
    rows["solid_fraction_interior"] = rows["solid_fraction"]
    table, trend = summarise(pd.DataFrame(rows))
    assert abs(trend[5.0]["slope"] + 0.2) < 3 * trend[5.0]["se"] and trend[5.0]["p"] < 1e-6
    assert trend[10.0]["p"] > 0.01 and abs(trend[10.0]["slope"]) < 3 * trend[10.0]["se"] + 1e-12
    assert list(table.n_rep) == [3] * 8
    np.testing.assert_allclose(table.order_sem, table.order_sd / np.sqrt(3))


def test_epd_order_command_writes_cases_and_collects_them(tmp_path, capsys):
    from ptrack.cli import main

    out = tmp_path / "o"
    args = ["study", "epd-order", "--no-dask", "--particles", "40", "--pe", "60", "180", "--replicates", "2",
            "--a-over-lambda", "5", "--out", str(out)]
    assert main(args + ["--json", str(tmp_path / "a.json")]) == 0
    assert len(list((out / "cases").glob("*.json"))) == 4 and not list((out / "cases").glob("*.ckpt.npz"))
    assert main(["study", "epd-order", "--collect", "--out", str(out), "--json", str(tmp_path / "b.json")]) == 0
    a, b = (json.loads((tmp_path / f).read_text()) for f in ("a.json", "b.json"))
    assert a["table"] == b["table"] and b["n_cases_finished"] == 4
    assert "a/lambda_D = 5: order" in capsys.readouterr().out
    assert (out / "epd_order.png").stat().st_size > 10000
    assert main(["study", "epd-order", "--collect", "--out", str(tmp_path / "none")]) == 2

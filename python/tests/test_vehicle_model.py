"""The vehicle model of a dataset and a parameter file: filter and smoother,
score by parameter name, metrics, training with a progress callback, the
diagnosis; and the same numbers as the `sefi` CLI on the same files."""

import json
import os
import pathlib
import subprocess

import numpy as np
import pytest

import pfsefi

ROOT = pathlib.Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def experiment():
    return pfsefi.generate_experiment("A", seed=1, quick=True)


@pytest.fixture(scope="module")
def model(experiment):
    train, _, params = experiment
    return pfsefi.VehicleModel(train, params)


def wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def test_filter_and_smoother_arrays(model, experiment):
    train = experiment[0]
    r = model.filter(particles=128, lag=4, seed=2)
    n, steps = train.num_objects, train.steps
    assert r["filtered"].shape == r["smoothed"].shape == (n, steps, 5)
    assert r["loglik_per_object"].shape == (n,)
    np.testing.assert_allclose(r["loglik"], r["loglik_per_object"].sum(), rtol=1e-12)
    assert r["observed_units"].sum() == train.num_observations
    # The evaluation's errors are those of these arrays against the truth.
    m = model.evaluate(particles=128, lag=4, seed=2)["runs"][0]
    assert m["log_likelihood"] == r["loglik"]
    for which in ["smoothed", "filtered"]:
        d = [np.hypot(*(r[which][i, :, :2] - train.truth(i)[:, :2]).T) for i in range(n)]
        yaw = [np.abs(wrap(r[which][i, :, 2] - train.truth(i)[:, 2])) for i in range(n)]
        np.testing.assert_allclose(m[which]["ade"], np.mean(np.concatenate(d)), rtol=1e-9)
        np.testing.assert_allclose(m[which]["aye"], np.mean(np.concatenate(yaw)), rtol=1e-9)
    # Under the true model the smoothed positions are closer to the truth than
    # the filtered ones (they also see later points).
    assert m["smoothed"]["ade"] < m["filtered"]["ade"]


def test_evaluate_summary_and_per_object(model):
    e = model.evaluate(particles=64, lag=4, seed=0, runs=2)
    assert len(e["runs"]) == 2 and e["runs"][0]["seed"] == 0 and e["runs"][1]["seed"] == 1
    run = e["runs"][0]
    np.testing.assert_allclose(run["mll"], run["log_likelihood"] / run["observed_units"], rtol=1e-12)
    np.testing.assert_allclose(e["per_object"]["loglik"].sum(), run["log_likelihood"], rtol=1e-12)
    assert e["summary"]["mll"]["n"] == 2
    assert run["aptll"]["mean"] is not None and run["aotll"]["mean"] is not None


def test_score_by_parameter_name_points_towards_the_truth(experiment):
    train, _, params = experiment
    names = set(params)
    r = pfsefi.VehicleModel(train, params).score(particles=256, lag=4, seed=3)
    assert set(r["score"]) <= names and "policy.log_sd" in r["score"]
    for name, g in r["score"].items():
        assert g.shape == params[name].shape and np.all(np.isfinite(g))
    again = pfsefi.VehicleModel(train, params).score(particles=256, lag=4, seed=3)
    np.testing.assert_array_equal(again["score"]["policy.log_sd"], r["score"]["policy.log_sd"])
    # With the policy's sds e times too large, the score in their logs is
    # negative: the likelihood rises towards the truth. (At the truth its
    # expectation is zero; one unit off, the drift dominates the Monte Carlo
    # noise of 256 particles over 20 objects many times over.)
    wide = dict(params)
    wide["policy.log_sd"] = params["policy.log_sd"] + 1.0
    g = pfsefi.VehicleModel(train, wide).score(particles=256, lag=4, seed=3)["score"]["policy.log_sd"]
    assert np.all(g < 0), g
    for est in ["pf", "dpf-sgr"]:
        b = pfsefi.VehicleModel(train, wide).score(estimator=est, particles=64, lag=4, seed=3)
        assert set(b["score"]) == set(r["score"])


def test_training_reports_progress_and_improves(experiment, tmp_path):
    train, test, _ = experiment
    # From the fresh models `sefi train` starts from (policy sds 2.0 and 0.2, a
    # random observation network): 4 epochs of the 2 training scenes.
    start = pfsefi.VehicleModel.initial(train, init_sd=(2.0, 0.2), seed=0)
    seen = []
    result = start.train(test, epochs=4, lr=0.02, particles=128, eval_particles=256, lag=4, seed=0,
                         eval_every=4, out=tmp_path / "run", callback=lambda step, loss: seen.append((step, loss)))
    assert [s for s, _ in seen] == list(range(1, result["steps"] + 1)) and result["steps"] == 8
    assert all(np.isfinite(loss) for _, loss in seen)
    evals = result["evaluations"]
    assert [s for s, _ in evals] == [0, 4, 8]
    assert evals[-1][1] == result["final_eval"]
    assert (tmp_path / "run" / "train.csv").is_file() and (tmp_path / "run" / "params.bin").is_file()
    np.testing.assert_array_equal(pfsefi.read_params(tmp_path / "run" / "params.bin")["policy.log_sd"],
                                  result["model"].parameters["policy.log_sd"])
    # The held-out MLL rises (measured over seeds 0-2 of this run: by 0.55 to
    # 0.75 nats per point, from about -2.0; its Monte Carlo noise at 256
    # particles is about 0.01), and the acceleration sd falls towards the
    # truth (about 0.5): Adam moves it by at most lr = 0.02 a step, so 8 steps
    # move it by at most 0.16 in its log; at least 0.05 of that is asked.
    assert evals[-1][1]["test_mll"] > evals[0][1]["test_mll"] + 0.2, evals
    moved = result["model"].parameters["policy.log_sd"][0] - np.log(2.0)
    assert moved < -0.05, moved
    with pytest.raises(FileExistsError, match="already"):
        start.train(test, epochs=1, particles=16, eval_particles=16, lag=2, out=tmp_path / "run")


def test_an_exception_in_the_callback_stops_training(experiment):
    train, test, params = experiment
    calls = []

    def stop(step, loss):
        calls.append(step)
        if step == 2:
            raise KeyError("enough at step 2")

    with pytest.raises(KeyError, match="enough at step 2"):
        pfsefi.VehicleModel(train, params).train(test, epochs=5, particles=32, eval_particles=32, lag=2, callback=stop)
    assert calls == [1, 2]
    with pytest.raises(ValueError, match="callback: must be callable"):
        pfsefi.VehicleModel(train, params).train(test, callback=3)


def test_parameter_files_and_errors(experiment, tmp_path):
    train, _, params = experiment
    pfsefi.write_params(params, tmp_path / "p.npz")
    from_file = pfsefi.VehicleModel(train, tmp_path / "p.npz")
    a = from_file.filter(particles=32, lag=2, seed=1)["loglik"]
    b = pfsefi.VehicleModel(train, params).filter(particles=32, lag=2, seed=1)["loglik"]
    assert a == b
    from_file.save_params(tmp_path / "q.bin")
    back = pfsefi.read_params(tmp_path / "q.bin")
    for k in params:
        np.testing.assert_array_equal(back[k], params[k])
    no_obs = {k: v for k, v in params.items() if not k.startswith("obs.")}
    with pytest.raises(ValueError, match="params"):
        pfsefi.VehicleModel(train, no_obs)
    bad = dict(params)
    bad["policy.log_sd"] = np.array([np.nan, 0.0])
    with pytest.raises(ValueError, match=r"policy.log_sd.*NaN"):
        pfsefi.VehicleModel(train, bad)
    with pytest.raises(FileNotFoundError):
        pfsefi.VehicleModel(train, tmp_path / "missing.npz")
    m = pfsefi.VehicleModel(train, params)
    with pytest.raises(ValueError, match="estimator"):
        m.score(estimator="nope")
    with pytest.raises(ValueError, match="particles: must be at least 1"):
        m.filter(particles=0)
    with pytest.raises(ValueError, match="filter: expected 'tempered' or 'bootstrap'"):
        m.filter(filter="other")


def test_initial_models():
    data = pfsefi.generate_hidden("none", scenes=1, objects=2, steps=4, seed=0)
    m = pfsefi.VehicleModel.initial(data, init_sd=(2.0, 0.2), seed=1)
    np.testing.assert_allclose(m.parameters["policy.log_sd"], np.log([2.0, 0.2]))
    assert m.policy == "hand-crafted"
    assert pfsefi.VehicleModel.initial(data, policy="neural").policy == "neural"
    with pytest.raises(ValueError, match="init_sd"):
        pfsefi.VehicleModel.initial(data, init_sd=(0.0, 1.0))


def sefi_binary():
    for candidate in [os.environ.get("SEFI"), ROOT / "target" / "release" / "sefi", ROOT / "target" / "debug" / "sefi"]:
        if candidate and pathlib.Path(candidate).is_file():
            return str(candidate)
    return None


@pytest.mark.skipif(sefi_binary() is None, reason="no sefi binary (cargo build -p experiments, or set SEFI)")
def test_same_log_likelihood_as_the_cli(experiment, tmp_path):
    train, _, params = experiment
    train.write(tmp_path / "data")
    pfsefi.write_params(params, tmp_path / "params.bin")
    subprocess.run(
        [sefi_binary(), "eval", "--data", str(tmp_path / "data"), "--params", str(tmp_path / "params.bin"),
         "--particles", "64", "--lag", "3", "--seed", "5", "--out", str(tmp_path / "eval")],
        check=True, capture_output=True,
    )
    cli = json.loads((tmp_path / "eval" / "metrics.json").read_text())["runs"][0]
    py = pfsefi.VehicleModel(pfsefi.Dataset.read(tmp_path / "data"), tmp_path / "params.bin").evaluate(
        particles=64, lag=3, seed=5)["runs"][0]
    assert py["log_likelihood"] == cli["log_likelihood"]
    assert py["observed_units"] == cli["observed_units"]
    assert py["smoothed"]["ade"] == cli["smoothed"]["ade"]


@pytest.mark.skipif(sefi_binary() is None, reason="no sefi binary (cargo build -p experiments, or set SEFI)")
def test_same_smoothed_states_as_the_cli_on_boxes(tmp_path):
    # Box detections (the other observation model, tempered with origin moves)
    # from a fresh model's parameters: `filter` gives `sefi track`'s states.
    data = pfsefi.generate_hidden("heading_flip", boxes=True, scenes=2, objects=3, steps=6, seed=3)
    data.write(tmp_path / "data")
    model = pfsefi.VehicleModel.initial(data, init_sd=(1.0, 0.1), seed=4)
    model.save_params(tmp_path / "params.bin")
    subprocess.run(
        [sefi_binary(), "track", "--data", str(tmp_path / "data"), "--params", str(tmp_path / "params.bin"),
         "--particles", "64", "--lag", "2", "--seed", "7", "--out", str(tmp_path / "track")],
        check=True, capture_output=True,
    )
    r = model.filter(particles=64, lag=2, seed=7)
    for which in ["smoothed", "filtered"]:
        cli = np.loadtxt(tmp_path / "track" / f"{which}.csv", delimiter=",", skiprows=1)
        np.testing.assert_array_equal(r[which].reshape(-1, 5), cli[:, 3:])
    metrics = json.loads((tmp_path / "track" / "track.json").read_text())["metrics"]
    assert r["loglik"] == metrics["log_likelihood"]


def test_diagnosis_report_as_a_dict(tmp_path):
    data = pfsefi.generate_hidden("none", scenes=4, objects=5, steps=8, seed=2)
    settings = dict(base_steps=6, candidate_steps=4, particles=32, eval_particles=64, draws=4, eval_runs=1,
                    scenes_per_step=2, keep_best_every=0)
    report = pfsefi.diagnose(data, tmp_path / "diag", seed=1, settings=settings)
    assert report["kind"] == "Points"
    assert report["train_objects"] + report["check_objects"] + report["eval_objects"] == data.num_objects
    assert isinstance(report["cause"], str) and isinstance(report["checks"], list) and report["checks"]
    with pytest.raises(ValueError, match='no setting named "no_such"'):
        pfsefi.diagnose(data, tmp_path / "d2", settings={"no_such": 1})
    with pytest.raises(ValueError, match="settings"):
        pfsefi.diagnose(data, tmp_path / "d3", settings={"fit_fraction": 2.0})


@pytest.mark.skipif(sefi_binary() is None, reason="no sefi binary (cargo build -p experiments, or set SEFI)")
def test_same_trained_parameters_as_the_cli(experiment, tmp_path):
    train, test, _ = experiment
    train.write(tmp_path / "train")
    test.write(tmp_path / "test")
    start = pfsefi.VehicleModel.initial(train, init_sd=(2.0, 0.2), seed=0)
    start.save_params(tmp_path / "init.bin")
    subprocess.run(
        [sefi_binary(), "train", "--data", str(tmp_path / "train"), "--test", str(tmp_path / "test"),
         "--init", str(tmp_path / "init.bin"), "--epochs", "2", "--lr", "0.02", "--particles", "32",
         "--eval-particles", "32", "--lag", "3", "--seed", "6", "--out", str(tmp_path / "cli")],
        check=True, capture_output=True,
    )
    cli = pfsefi.read_params(tmp_path / "cli" / "params.bin")
    result = start.train(test, epochs=2, lr=0.02, particles=32, eval_particles=32, lag=3, seed=6)
    mine = result["model"].parameters
    assert list(mine) == list(cli)
    for name in cli:
        np.testing.assert_array_equal(mine[name], cli[name], err_msg=name)
    assert not np.array_equal(mine["policy.log_sd"], start.parameters["policy.log_sd"])

"""Datasets: the project's format read and written, built from arrays, generated
(experiments A/B, hidden effects) and imported from KITTI; errors that say where."""

import os
import pathlib

import numpy as np
import pytest

import pfsefi

KITTI = pathlib.Path(os.environ.get("PFSEFI_KITTI", "/work/shared/data/kitti-tracking"))


@pytest.fixture(scope="module")
def hidden_points():
    return pfsefi.generate_hidden("clutter", scenes=2, objects=3, steps=6, seed=4)


@pytest.fixture(scope="module")
def hidden_boxes():
    return pfsefi.generate_hidden("heading_flip", boxes=True, scenes=2, objects=3, steps=6, seed=5)


def tiny_tables():
    """One scene of 3 steps, one object, three points and its true states."""
    av = np.array([[7, t, 0.5 * t, 0.0, 0.0] for t in range(3)], dtype=float)
    objects = np.array([[7, 1, 4.5, 1.8, 10.0, 2.0, 0.1, 5.0, 0.0, 1.0, 1.0, 0.2, 2.0, 0.01]])
    points = np.array([[7, 1, 0, 10.2, 2.1], [7, 1, 2, 11.1, 2.0], [7, 1, 2, 10.9, 1.7]])
    states = np.array([[7, 1, t, 10.0 + 0.5 * t, 2.0, 0.1, 5.0, 0.0] for t in range(3)])
    return dict(av=av, objects=objects, points=points, states=states)


def test_columns_are_those_of_the_files():
    assert pfsefi.COLUMNS["points"] == ["scene", "object", "t", "x", "y"]
    assert pfsefi.COLUMNS["objects"][:4] == ["scene", "object", "length", "width"]
    assert len(pfsefi.COLUMNS["objects"]) == 14


def test_built_from_arrays_and_read_back(tmp_path):
    ds = pfsefi.Dataset.from_arrays(0.1, **tiny_tables())
    assert (ds.kind, ds.num_scenes, ds.num_objects, ds.steps, ds.dt) == ("points", 1, 1, 3, 0.1)
    assert ds.num_observations == 3 and ds.has_truth
    np.testing.assert_array_equal(ds.object_ids, [[7, 1]])
    obs = ds.observations(0)
    np.testing.assert_array_equal(obs, [[0, 10.2, 2.1], [2, 11.1, 2.0], [2, 10.9, 1.7]])
    np.testing.assert_allclose(ds.truth(0)[:, 0], [10.0, 10.5, 11.0])
    assert ds.actions(0) is None
    ds.write(tmp_path / "tiny")
    lines = (tmp_path / "tiny" / "points.csv").read_text().splitlines()
    assert lines[0] == "scene,object,t,x,y" and len(lines) == 4
    back = pfsefi.Dataset.read(tmp_path / "tiny")
    assert back == ds
    np.testing.assert_array_equal(back.observations(0), obs)


@pytest.mark.parametrize("which", ["hidden_points", "hidden_boxes"])
def test_round_trips(which, request, tmp_path):
    ds = request.getfixturevalue(which)
    ds.write(tmp_path / "d")
    back = pfsefi.Dataset.read(tmp_path / "d")
    assert back == ds
    tables = ds.tables()
    for name, table in back.tables().items():
        np.testing.assert_array_equal(table, tables[name])
    rebuilt = pfsefi.Dataset.from_arrays(ds.dt, **tables, prior_from_detection=ds.prior_from_detection)
    assert rebuilt == ds


def test_object_arrays_match_the_tables(hidden_points, hidden_boxes):
    ds = hidden_points
    points = ds.tables()["points"]
    states = ds.tables()["states"]
    for i, (scene, obj) in enumerate(ds.object_ids):
        mine = points[(points[:, 0] == scene) & (points[:, 1] == obj)]
        np.testing.assert_array_equal(ds.observations(i), mine[:, 2:])
        st = states[(states[:, 0] == scene) & (states[:, 1] == obj)]
        np.testing.assert_array_equal(ds.truth(i), st[np.argsort(st[:, 2]), 3:])
    assert sum(len(ds.observations(i)) for i in range(ds.num_objects)) == ds.num_observations
    b = hidden_boxes
    assert b.kind == "boxes"
    seen = sum(int(np.sum(~np.isnan(b.observations(i)[:, 0]))) for i in range(b.num_objects))
    assert seen == b.num_observations
    assert b.observations(0).shape == (b.steps, 6)
    with pytest.raises(ValueError, match="object: index 99 out of range"):
        b.observations(99)


def test_generated_experiment_is_seeded():
    train, test, params = pfsefi.generate_experiment("A", seed=2, quick=True)
    assert train.has_truth and test.has_truth and train.kind == "points"
    assert train.num_scenes == 2 and test.num_scenes == 1
    assert "policy.log_sd" in params and params["policy.log_sd"].shape == (2,)
    again, _, _ = pfsefi.generate_experiment("A", seed=2, quick=True)
    other, _, _ = pfsefi.generate_experiment("A", seed=3, quick=True)
    assert again == train and other != train
    with pytest.raises(ValueError, match="experiment"):
        pfsefi.generate_experiment("Z", quick=True)


def test_hidden_effect_names_are_checked():
    with pytest.raises(ValueError, match="effect"):
        pfsefi.generate_hidden("no_such_effect")
    a = pfsefi.generate_hidden("none", scenes=1, objects=2, steps=4, seed=1)
    b = pfsefi.generate_hidden("latency", scenes=1, objects=2, steps=4, seed=1)
    assert a.num_objects == b.num_objects == 2 and a != b


def test_bad_file_names_file_line_and_column(hidden_points, tmp_path):
    d = tmp_path / "bad"
    hidden_points.write(d)
    lines = (d / "objects.csv").read_text().splitlines()
    header = lines[0].split(",")
    row = lines[2].split(",")
    row[header.index("width")] = "wide"
    lines[2] = ",".join(row)
    (d / "objects.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(pfsefi.DataError) as info:
        pfsefi.Dataset.read(d)
    e = info.value
    assert (e.file, e.line, e.column) == ("objects.csv", 3, "width")
    assert "objects.csv" in str(e) and "line 3" in str(e) and "width" in str(e)
    assert isinstance(e, ValueError)
    with pytest.raises(FileNotFoundError):
        pfsefi.Dataset.read(tmp_path / "nowhere")


def test_bad_tables():
    t = tiny_tables()
    with pytest.raises(ValueError, match=r"objects: expected shape \(rows, 14\)"):
        pfsefi.Dataset.from_arrays(0.1, **{**t, "objects": t["objects"][:, :5]})
    with pytest.raises(TypeError, match="points: expected a floating-point array"):
        pfsefi.Dataset.from_arrays(0.1, **{**t, "points": t["points"].astype(np.int64)})
    nan = t["points"].copy()
    nan[1, 3] = np.nan
    with pytest.raises(ValueError, match=r"points: entry \[1, 3\] is NaN"):
        pfsefi.Dataset.from_arrays(0.1, **{**t, "points": nan})
    frac = t["points"].copy()
    frac[2, 2] = 1.5
    with pytest.raises(ValueError, match="points: row 2, column `t`: expected an integer, got 1.5"):
        pfsefi.Dataset.from_arrays(0.1, **{**t, "points": frac})
    with pytest.raises(ValueError, match="av: the array is empty"):
        pfsefi.Dataset.from_arrays(0.1, **{**t, "av": np.zeros((0, 5))})
    with pytest.raises(ValueError, match="exactly one of them"):
        pfsefi.Dataset.from_arrays(0.1, t["av"], t["objects"])
    with pytest.raises(ValueError, match="scene 7 has no pose at t = 1"):
        pfsefi.Dataset.from_arrays(0.1, **{**t, "av": t["av"][[0, 2]]})
    # A record the format refuses names its table (as the file it would be
    # written to), its row and column; there is no line.
    neg = t["objects"].copy()
    neg[0, 2] = -1.0
    with pytest.raises(pfsefi.DataError) as info:
        pfsefi.Dataset.from_arrays(0.1, **{**t, "objects": neg})
    assert (info.value.file, info.value.line, info.value.column) == ("objects.csv", None, "length")
    assert "record 0" in str(info.value)
    late = t["points"].copy()
    late[0, 2] = 3
    with pytest.raises(pfsefi.DataError) as info:
        pfsefi.Dataset.from_arrays(0.1, **{**t, "points": late})
    assert info.value.file == "points.csv" and info.value.column == "t"


def test_select():
    ds = pfsefi.Dataset.from_arrays(0.1, **tiny_tables())
    assert ds.select_objects([0]) == ds
    with pytest.raises(ValueError, match="out of range"):
        ds.select_scenes([3])


@pytest.mark.skipif(not (KITTI / "label_02").is_dir(), reason="KITTI tracking data not present (set PFSEFI_KITTI)")
def test_kitti_import():
    train, val, report = pfsefi.import_kitti(KITTI, steps=10, sequences=[0, 1], val_sequences=[1])
    assert train.kind == val.kind == "boxes"
    assert train.prior_from_detection and train.steps == 10 and abs(train.dt - 0.1) < 1e-12
    assert train.num_objects > 0 and val.num_objects > 0 and train.has_truth
    assert "KITTI import" in report and "| objects (track windows) |" in report
    # Every object's first step is detected (its prior is read from it).
    assert not np.isnan(train.observations(0)[0, 0])
    with pytest.raises(ValueError):
        pfsefi.import_kitti(KITTI, steps=0)

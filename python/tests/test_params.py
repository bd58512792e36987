"""Parameter files: .npz and the project's format, round trips and errors."""

import numpy as np
import pytest

import pfsefi

PARAMS = {"theta": np.array([0.5, -1.25, 1e-300]), "net.w": np.arange(6.0).reshape(2, 3), "s": np.array(7.0)}


def test_npz_round_trip_and_numpy_reads_it(tmp_path):
    path = tmp_path / "p.npz"
    pfsefi.write_params(PARAMS, path)
    with np.load(path) as z:
        assert list(z.keys()) == list(PARAMS)
        for k, v in PARAMS.items():
            np.testing.assert_array_equal(z[k], v)
            assert z[k].shape == v.shape and z[k].dtype == np.float64
    back = pfsefi.read_params(path)
    assert list(back) == list(PARAMS)
    for k, v in PARAMS.items():
        np.testing.assert_array_equal(back[k], v)


def test_reads_what_numpy_savez_writes(tmp_path):
    path = tmp_path / "np.npz"
    np.savez(path, a=np.linspace(0, 1, 5), b=np.ones((2, 2), dtype=np.float32))
    back = pfsefi.read_params(path)
    np.testing.assert_array_equal(back["a"], np.linspace(0, 1, 5))
    assert back["b"].shape == (2, 2)


def test_bincode_and_npz_convert_both_ways(tmp_path):
    bin_path, npz_path, again = tmp_path / "p.bin", tmp_path / "p.npz", tmp_path / "q.bin"
    pfsefi.write_params(PARAMS, bin_path)
    pfsefi.convert_params(bin_path, npz_path)
    pfsefi.convert_params(npz_path, again, like=bin_path)
    assert again.read_bytes() == bin_path.read_bytes()


def test_scene_parameters_export(tmp_path):
    scene = pfsefi.SyntheticScene(transitions=3, seed=1)
    scene.save_params(tmp_path / "truth.bin")
    pfsefi.convert_params(tmp_path / "truth.bin", tmp_path / "truth.npz")
    with np.load(tmp_path / "truth.npz") as z:
        assert set(z.keys()) == set(scene.parameters)


def test_errors_name_the_file(tmp_path):
    with pytest.raises(OSError, match=r"missing.npz"):
        pfsefi.read_params(tmp_path / "missing.npz")
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(ValueError, match=r"bad.npz: not a readable .npz"):
        pfsefi.read_params(bad)
    comp = tmp_path / "comp.npz"
    np.savez_compressed(comp, a=np.ones(100))
    with pytest.raises(ValueError, match=r"comp.npz: entry \"a.npy\": compressed"):
        pfsefi.read_params(comp)
    ints = tmp_path / "ints.npz"
    np.savez(ints, a=np.arange(3))
    with pytest.raises(ValueError, match=r"ints.npz: entry \"a.npy\": dtype '<i8'"):
        pfsefi.read_params(ints)
    corrupt = tmp_path / "c.bin"
    corrupt.write_bytes(b"garbage")
    with pytest.raises(ValueError, match=r"c.bin: corrupt parameter file"):
        pfsefi.read_params(corrupt)
    with pytest.raises(ValueError, match=r"params\[\"x\"\]: entry \[1\] is NaN"):
        pfsefi.write_params({"x": np.array([1.0, np.nan])}, tmp_path / "x.npz")
    with pytest.raises(ValueError, match=r"params: the dict is empty"):
        pfsefi.write_params({}, tmp_path / "x.npz")
    pfsefi.write_params({"theta": np.zeros(2)}, tmp_path / "small.npz")
    pfsefi.write_params(PARAMS, tmp_path / "like.bin")
    with pytest.raises(ValueError, match=r"small.npz"):
        pfsefi.convert_params(tmp_path / "small.npz", tmp_path / "out.bin", like=tmp_path / "like.bin")

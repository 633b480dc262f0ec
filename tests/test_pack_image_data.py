"""Packing a rendered image dataset for a transfer limit: lossless round trip, checked on unpack."""
import importlib.util
import lzma
from pathlib import Path

import h5py
import numpy as np
import pytest

_spec = importlib.util.spec_from_file_location(
    "pack_image_data", Path(__file__).resolve().parents[1] / "scripts" / "pack_image_data.py")
pack_image_data = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(pack_image_data)


def _dataset(path: Path) -> None:
    rng = np.random.default_rng(0)
    with h5py.File(path, "w") as f:
        data = f.create_group("data")
        data.attrs["env_args"] = '{"env_name": "Lift"}'
        for i, n in enumerate((3, 5)):
            demo = data.create_group(f"demo_{i}")
            demo.attrs["num_samples"] = n
            demo.create_dataset("actions", data=rng.normal(size=(n, 7)))
            obs = demo.create_group("obs")
            obs.create_dataset("robot0_eef_pos", data=rng.normal(size=(n, 3)))
            for cam in ("agentview_image", "robot0_eye_in_hand_image"):
                obs.create_dataset(cam, data=rng.integers(0, 255, (n, 6, 6, 3), dtype=np.uint8),
                                   compression="gzip", chunks=(1, 6, 6, 3))


def _contents(path: Path) -> dict:
    out = {}
    with h5py.File(path, "r") as f:
        f.visititems(lambda name, obj: out.__setitem__(name, obj[()] if isinstance(obj, h5py.Dataset)
                                                       else dict(obj.attrs)))
        out["/"] = dict(f.attrs)
    return out


def test_pack_then_unpack_gives_the_same_dataset_and_a_changed_frame_is_an_error(tmp_path):
    src, packed, back = tmp_path / "images.hdf5", tmp_path / "pack", tmp_path / "back.hdf5"
    _dataset(src)
    manifest = pack_image_data.pack(src, packed)
    assert manifest["cameras"]["agentview_image"]["lengths"] == [3, 5]
    assert sorted(p.name for p in packed.iterdir()) == [
        "agentview_image.u8.xz", "manifest.json", "rest.hdf5", "robot0_eye_in_hand_image.u8.xz"]
    with h5py.File(packed / "rest.hdf5", "r") as f:  # the frames travel only once
        assert "agentview_image" not in f["data/demo_0/obs"] and "robot0_eef_pos" in f["data/demo_0/obs"]
    pack_image_data.unpack(packed, back)
    a, b = _contents(src), _contents(back)
    assert a.keys() == b.keys()
    for k in a:
        if isinstance(a[k], dict):
            assert a[k] == b[k], k
        else:
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    frames = np.frombuffer(lzma.decompress((packed / "agentview_image.u8.xz").read_bytes()), np.uint8).copy()
    frames[0] ^= 1
    (packed / "agentview_image.u8.xz").write_bytes(lzma.compress(frames.tobytes()))
    with pytest.raises(SystemExit, match="do not match"):
        pack_image_data.unpack(packed, tmp_path / "bad.hdf5")
    assert not (tmp_path / "bad.hdf5").exists() and not (tmp_path / "bad.partial").exists()

"""Pack a rendered image dataset (robomimic layout, eval/render_demos.py) small enough to carry to a
machine with a transfer limit, and unpack it there, losslessly.

    python scripts/pack_image_data.py pack data/lift_expert_image.hdf5 build/pack
    python scripts/pack_image_data.py unpack build/pack data/lift_expert_image.hdf5

``pack`` writes the dataset without its camera frames (``rest.hdf5``), each camera's frames of all
demos end to end as one xz stream (``<camera>.u8.xz``: whole-array LZMA compresses these renders
2-7x better than the per-frame gzip chunks of the layout) and a manifest with the demo order,
shapes and the SHA-256 of every camera's frames. ``unpack`` rebuilds the dataset with the frames in
their demos (per-frame gzip chunks again) and checks the hashes: a mismatch is an error.
"""
from __future__ import annotations

import hashlib
import json
import lzma
import shutil
import sys
from pathlib import Path

import h5py
import numpy as np


def _image_keys(group: h5py.Group) -> list[str]:
    return sorted(k for k in group["obs"] if k.endswith("_image"))


def pack(src: Path, out: Path) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    with h5py.File(src, "r") as f:
        demos = list(f["data"].keys())
        cameras = _image_keys(f["data"][demos[0]])
        manifest = {"source": str(src), "demos": demos, "cameras": {}}
        for cam in cameras:
            frames = [f["data"][d]["obs"][cam][:] for d in demos]
            whole = np.ascontiguousarray(np.concatenate(frames))
            (out / f"{cam}.u8.xz").write_bytes(lzma.compress(whole.tobytes(), preset=6))
            manifest["cameras"][cam] = {"lengths": [len(x) for x in frames], "frame_shape": list(whole.shape[1:]),
                                        "sha256": hashlib.sha256(whole.tobytes()).hexdigest()}
    rest = out / "rest.hdf5"
    shutil.copyfile(src, rest)
    with h5py.File(rest, "a") as f:
        for d in f["data"]:
            for cam in cameras:
                del f["data"][d]["obs"][cam]
    _repack(rest)
    (out / "manifest.json").write_text(json.dumps(manifest))
    return manifest


def _repack(path: Path) -> None:
    """Copy into a fresh file (deleting datasets does not shrink an HDF5 file)."""
    tmp = path.with_suffix(".tmp")
    with h5py.File(path, "r") as src, h5py.File(tmp, "w") as dst:
        for k, v in src.attrs.items():
            dst.attrs[k] = v
        for k in src:
            src.copy(src[k], dst, name=k)
    tmp.replace(path)


def unpack(folder: Path, out: Path) -> None:
    manifest = json.loads((folder / "manifest.json").read_text())
    tmp = out.with_suffix(".partial")
    shutil.copyfile(folder / "rest.hdf5", tmp)
    try:
        with h5py.File(tmp, "a") as f:
            for cam, info in manifest["cameras"].items():
                whole = np.frombuffer(lzma.decompress((folder / f"{cam}.u8.xz").read_bytes()), dtype=np.uint8)
                if hashlib.sha256(whole.tobytes()).hexdigest() != info["sha256"]:
                    raise SystemExit(f"{cam}: the unpacked frames do not match the packed ones")
                whole = whole.reshape(-1, *info["frame_shape"])
                start = 0
                for demo, n in zip(manifest["demos"], info["lengths"]):
                    f["data"][demo]["obs"].create_dataset(cam, data=whole[start:start + n], compression="gzip",
                                                          compression_opts=4, chunks=(1, *info["frame_shape"]))
                    start += n
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    tmp.replace(out)


if __name__ == "__main__":
    if len(sys.argv) != 4 or sys.argv[1] not in ("pack", "unpack"):
        raise SystemExit(__doc__)
    (pack if sys.argv[1] == "pack" else unpack)(Path(sys.argv[2]), Path(sys.argv[3]))

"""FID and sFID of a set of samples against a reference, fully offline (eval/image_suite/fid.py).

    python eval/fid.py --samples samples.npz --ref REF [--ref-cache ref_stats.npz] [--inception PATH] [--json out.json]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Optional, Sequence, Union

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import write_json  # noqa: E402
from image_suite.fid import (PREPROCESS_MODES, Stats, _npz_has_stats, compute_stats, fid_sfid,  # noqa: E402
                             load_inception, reference_stats)


def main(argv: Optional[Sequence[str]] = None) -> int:
    """CLI: print FID/sFID of --samples against --ref as JSON (and write it to --json)."""
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--samples", required=True, help="uint8 images: .npz (arr_0 [N,H,W,3]), .npy or a folder; "
                                                     "or a stats .npz (mu, sigma, ...)")
    ap.add_argument("--ref", required=True, help="ADM reference batch / stats .npz, an image .npz/.npy, or a folder")
    ap.add_argument("--ref-cache", help="where to save/reuse the reference stats computed from images (.npz)")
    ap.add_argument("--save-stats", help="also save the samples' stats to this .npz")
    ap.add_argument("--inception", help="Inception weights: fid-helper default_1.pt or a converted .pth")
    ap.add_argument("--json", help="write the result (with provenance) to this JSON file")
    ap.add_argument("--batch-size", type=int, default=50)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--preprocess", choices=PREPROCESS_MODES, default="adm")
    ap.add_argument("--threads", type=int, help="torch.set_num_threads")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)

    import torch

    if args.threads:
        torch.set_num_threads(args.threads)
    t0 = time.time()
    progress = not args.no_progress
    model = load_inception(args.inception, device=args.device)
    ref = reference_stats(args.ref, cache=args.ref_cache, model=model, batch_size=args.batch_size,
                          preprocess_mode=args.preprocess, progress=progress)
    samples: Union[str, Stats] = args.samples
    sp = Path(args.samples)
    if not (sp.suffix == ".npz" and sp.is_file() and _npz_has_stats(sp)):
        samples = compute_stats(args.samples, model, args.batch_size, args.preprocess, progress, desc="samples",
                                meta={"source": str(sp.resolve())})
        if args.save_stats:
            samples.save(args.save_stats)
    result = fid_sfid(samples, ref, model=model)
    print(json.dumps(result))
    if args.json:
        write_json(args.json, dict(result, samples=str(args.samples), ref=str(args.ref),
                                   inception=model.weights_source, preprocess=args.preprocess,
                                   torch=torch.__version__, seconds=round(time.time() - t0, 2),
                                   date=time.strftime("%Y-%m-%dT%H:%M:%S%z")))
    return 0


if __name__ == "__main__":
    sys.exit(main())

import json, sys
from pathlib import Path
import torch
from naka_gs_plugin.data.images import read_rgb
from naka_gs_plugin.enhance.checkpoint import load_correction
from naka_gs_plugin.enhance.correction import CorrectionRunner
from naka_gs_plugin.enhance.naka import naka_enhance
torch.set_grad_enabled(False)
for scene in sys.argv[1:]:
    root = Path("../shared/data/lom") / scene
    runner = CorrectionRunner(load_correction(f"outputs/correction-loo/{scene}/best.pt"), "auto")
    out = {}
    for split in ("train", "test"):
        for frame in json.loads((root / f"transforms_{split}.json").read_text())["frames"]:
            name = Path(frame["file_path"]).name
            low = torch.from_numpy(read_rgb(root / "low" / name))
            naka = naka_enhance(low, 0.05)
            enh = runner(low.permute(2, 0, 1)[None], naka.permute(2, 0, 1)[None])["enhanced"][0].permute(1, 2, 0).clamp(0,1)
            truth = torch.from_numpy(read_rgb(root / "high" / name))
            out[name] = dict(split=split, low=low.half(), naka=naka.half(), net=enh.half(), truth=truth.half())
    torch.save(out, f"/tmp/exp/{scene}.pt")
    print(scene, len(out), flush=True)

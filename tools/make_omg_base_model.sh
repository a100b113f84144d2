#!/usr/bin/env bash
# Full-size random-weight OMG-Base model file for benchmarks (f32, git-ignored):
#   models/omg_base_random.safetensors  the paper's Base backbone (8 x 1024, 8 heads) with a
#                                       ControlNet and MoC on every block (d_m 256, 12 experts)
#                                       + a CLIP ViT-L/14-sized text tower
# A state dict of tools/reference/omg.py's OMG("base") (PyTorch's default initialisation: every
# weight nonzero, the up-projections too) -> tools/convert.py omg, as a trained checkpoint would
# be converted. The intermediate folder is deleted unless KEEP_CKPT=1.
# Usage: tools/make_omg_base_model.sh [extra convert.py args, e.g. --dtype f16]
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
mkdir -p models
out=models/omg_base_random.safetensors
work=models/.omg_base_random.work
mkdir -p "$work"

"$PY" - "$work" <<'PYEOF'
import os, sys
import numpy as np
import torch
sys.path.insert(0, "tools")
from reference import omg
from make_latent_checkpoints import write_clip

work = sys.argv[1]
torch.manual_seed(0)
net = omg.OMG("base")
torch.save(net.state_dict(), os.path.join(work, "omg.pt"))
write_clip(os.path.join(work, "clip"), "mld", 0)  # ViT-L/14 text tower sizes (768 wide)
rng = np.random.default_rng(0)
np.save(os.path.join(work, "mean.npy"), rng.normal(0, 0.5, 263).astype(np.float32))
np.save(os.path.join(work, "std.npy"), rng.uniform(0.5, 1.5, 263).astype(np.float32))
PYEOF
"$PY" tools/convert.py omg --ckpt "$work/omg.pt" --clip "$work/clip" --mean "$work/mean.npy" \
    --std "$work/std.npy" --preset base --out "$out" "$@"
if [ "${KEEP_CKPT:-0}" != 1 ]; then rm -rf "$work"; fi
ls -l "$out"

"""The open_clip side of `cargo xtask bench -p rlmflow-torch --bench open_clip`: loads an encoder
directory's `open_clip.json` and `model.safetensors` into open_clip 3.3 exactly as the README
shows, embeds the frames and captions of `inputs.safetensors` and prints the largest absolute
difference from rlmflow's embeddings (and their largest magnitude, for scale).

    python open_clip_reference.py ENCODER_DIR
"""

import json
import sys

import open_clip
import safetensors.torch
import torch
from open_clip.transformer import QuickGELU

encoder = sys.argv[1]
torch.set_num_threads(2)

# The README's loading lines.
model = open_clip.CLIP(**json.load(open(f"{encoder}/open_clip.json")))
weights = safetensors.torch.load_file(f"{encoder}/model.safetensors")
weights["visual.conv1.weight"] = weights["visual.conv1.weight"].repeat(1, 3, 1, 1) / 3
model.load_state_dict(weights)
for block in model.transformer.resblocks:
    block.mlp.gelu = QuickGELU()
model.eval()

inputs = safetensors.torch.load_file(f"{encoder}/inputs.safetensors")
with torch.no_grad():
    image = model.encode_image(inputs["images"].repeat(1, 3, 1, 1))
    text = model.encode_text(inputs["tokens"])
differences = [
    (image - inputs["image_embedding"]).abs().max().item(),
    (text - inputs["text_embedding"]).abs().max().item(),
]
scale = max(inputs["image_embedding"].abs().max().item(), inputs["text_embedding"].abs().max().item())
print(f"largest |open_clip - rlmflow|: radar {differences[0]:.2e}, text {differences[1]:.2e} (embeddings up to {scale:.2f})")

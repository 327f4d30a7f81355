"""The PyTorch reference for `cargo xtask bench -p rlmflow-torch --bench step`: the same towers,
SG-CLIP loss, clipping and AdamW step as rlmflow-nn, written in plain PyTorch the way open_clip
writes them. Needs torch 2.11 (`import torch`); CI never runs it.

    python step_reference.py '<model config JSON>' BATCH STEPS THREADS [DEVICE [PRECISION]]

prints the median milliseconds per training step (the device synchronised). DEVICE is cpu or
cuda; PRECISION fp32, tf32 or bf16 (the towers and loss under torch.autocast in bfloat16, as
open_clip's `--precision amp_bf16`; weights, optimiser and clipping in float32). On CUDA it runs
with deterministic algorithms, as rlmflow does.
"""

import json
import os
import sys
import time

import torch
import torch.nn.functional as F
from torch import nn


class Block(nn.Module):
    def __init__(self, width, heads, mlp, quick_gelu):
        super().__init__()
        self.heads, self.quick_gelu = heads, quick_gelu
        self.ln_1, self.ln_2 = nn.LayerNorm(width), nn.LayerNorm(width)
        self.in_proj = nn.Linear(width, 3 * width)
        self.out_proj = nn.Linear(width, width)
        self.c_fc, self.c_proj = nn.Linear(width, mlp), nn.Linear(mlp, width)

    def forward(self, x, causal):
        b, t, w = x.shape
        q, k, v = self.in_proj(self.ln_1(x)).split(w, -1)
        split = lambda z: z.view(b, t, self.heads, w // self.heads).transpose(1, 2)
        a = F.scaled_dot_product_attention(split(q), split(k), split(v), is_causal=causal)
        x = x + self.out_proj(a.transpose(1, 2).reshape(b, t, w))
        h = self.c_fc(self.ln_2(x))
        h = h * torch.sigmoid(1.702 * h) if self.quick_gelu else F.gelu(h)
        return x + self.c_proj(h)


class Vision(nn.Module):
    def __init__(self, c, embed):
        super().__init__()
        stem = c["stem"]
        if stem["type"] == "patch":
            self.stem = nn.Conv2d(1, c["width"], stem["size"], stem["size"], bias=False)
        else:
            layers, channels = [], 1
            for out in stem["channels"]:
                layers += [nn.Conv2d(channels, out, 3, 2, 1, bias=False), nn.BatchNorm2d(out), nn.GELU()]
                channels = out
            self.stem = nn.Sequential(*layers)
        grid = c["image"] // stem["size"] if stem["type"] == "patch" else c["image"] // 2 ** len(stem["channels"])
        self.cls = nn.Parameter(torch.randn(c["width"]) * 0.02)
        self.pos = nn.Parameter(torch.randn(grid * grid + 1, c["width"]) * 0.02)
        self.ln_pre, self.ln_post = nn.LayerNorm(c["width"]), nn.LayerNorm(c["width"])
        self.blocks = nn.ModuleList(Block(c["width"], c["heads"], c["mlp"], False) for _ in range(c["layers"]))
        self.proj = nn.Parameter(torch.randn(c["width"], embed) * 0.02)

    def forward(self, x):
        x = self.stem(x).flatten(2).transpose(1, 2)
        x = torch.cat([self.cls.expand(x.shape[0], 1, -1), x], 1) + self.pos
        x = self.ln_pre(x)
        for block in self.blocks:
            x = block(x, False)
        return self.ln_post(x)[:, 0] @ self.proj


class Text(nn.Module):
    def __init__(self, c, embed):
        super().__init__()
        self.c = c
        self.token_embedding = nn.Embedding(c["vocab"], c["token_width"])
        self.group = nn.Linear(c["group"] * c["token_width"], c["width"]) if c["group"] > 1 else None
        self.pos = nn.Parameter(torch.randn(c["context"] // c["group"], c["width"]) * 0.01)
        self.blocks = nn.ModuleList(Block(c["width"], c["heads"], c["mlp"], True) for _ in range(c["layers"]))
        self.ln_final = nn.LayerNorm(c["width"])
        self.proj = nn.Parameter(torch.randn(c["width"], embed) * 0.02)

    def forward(self, tokens):
        b, t = tokens.shape
        x = self.token_embedding(tokens)
        if self.group is not None:
            x = self.group(x.view(b, t // self.c["group"], -1))
        x = x + self.pos
        for block in self.blocks:
            x = block(x, True)
        x = self.ln_final(x)
        end = (tokens == self.c["end_token"]).int().argmax(1) // self.c["group"]
        return x[torch.arange(b, device=x.device), end] @ self.proj


def main():
    config, batch, steps, threads = json.loads(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
    device = torch.device(sys.argv[5] if len(sys.argv) > 5 else "cpu")
    precision = sys.argv[6] if len(sys.argv) > 6 else "fp32"
    torch.set_num_threads(threads)
    torch.manual_seed(0)
    if device.type == "cuda":
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
        torch.use_deterministic_algorithms(True)
        torch.backends.cudnn.benchmark = False
        torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = precision == "tf32"
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    vision, text = Vision(config["vision"], config["embed"]).to(device), Text(config["text"], config["embed"]).to(device)
    params = list(vision.parameters()) + list(text.parameters())
    decay = [p for p in params if p.dim() >= 2]
    rest = [p for p in params if p.dim() < 2]
    opt = torch.optim.AdamW([{"params": decay, "weight_decay": 0.05}, {"params": rest, "weight_decay": 0.0}], lr=1e-4, betas=(0.9, 0.98), eps=1e-8)
    side, ctx = config["vision"]["image"], config["text"]["context"]
    images = (torch.randint(0, 256, (batch, 1, side, side)).float() / 127.5 - 1).to(device)
    tokens = torch.randint(3, config["text"]["vocab"], (batch, ctx))
    tokens[:, ctx // 2] = config["text"]["end_token"]
    tokens = tokens.to(device)
    counts = torch.randint(0, 3, (batch, 48)).float().to(device)
    times = []
    for _ in range(steps + 2):
        sync()
        t0 = time.perf_counter()
        with torch.autocast(device.type, torch.bfloat16, enabled=precision == "bf16"):
            img, txt = vision(images), text(tokens)
            logits = F.normalize(img, dim=-1) @ F.normalize(txt, dim=-1).T / 0.07
            d = (counts[:, None] - counts[None]).abs().sum(-1)
            s = torch.exp(-4.0 * d**2)
            target = s / s.sum(1, keepdim=True)
            tt = target.T / target.T.sum(1, keepdim=True)
            loss = (-(target * logits.log_softmax(1)).sum(1).mean() - (tt * logits.T.log_softmax(1)).sum(1).mean()) / 2
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, 1.0)
        opt.step()
        sync()
        times.append(time.perf_counter() - t0)
    times = sorted(times[2:])
    print(1000 * times[len(times) // 2])


main()

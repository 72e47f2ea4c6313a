"""The plan of ``pipeline: sr`` (``tiledsm sr`` and ``tiledsm run``): the
image and its camera open, the network has weights at the scale (or x2
weights applied repeatedly, or a weights file), the device exists, an
earlier run in the folder is one of the same recipe (or ``--overwrite``),
and the lazy tiled graph is built and counted (:attr:`Plan.product`)."""

from __future__ import annotations

from typing import Sequence

from tiledsm.errors import InvalidOptionError
from tiledsm.plan.core import InputInfo, Plan, check_earlier_run, existing_file, namer, readable_raster

__all__ = ["plan_sr", "check_sr_weights"]


def plan_sr(plan: Plan, recipe, cluster=None, *, overwrite: bool = False, names=None) -> Plan:
    """Fill ``plan`` (made by :func:`tiledsm.pipelines.plan_recipe`: workers,
    scheduler and the folder's lock checked) for a
    :class:`~tiledsm.sr.recipe.SRRecipe`.

    Messages name the command's options when ``tiledsm sr`` built the
    recipe (``plan.command``), the recipe's field paths otherwise;
    ``names`` (the DSM stage's spellings) is not used.

    Returns
    -------
    Plan
        ``plan``, with :attr:`Plan.product` the lazy super-resolved image
        (:func:`tiledsm.sr.infer.super_resolve`), float32, ``scale`` times
        the input's rows and columns.

    Raises
    ------
    InputFileError, InvalidOptionError, SRError
    """
    from tiledsm.sr.recipe import SRRecipe, product_name

    spelled = namer(SRRecipe, plan)
    spec = recipe.sr
    image = spelled("input.image")
    src = readable_raster(existing_file(recipe.input.image, image), image)
    if spec.device == "cuda":
        import torch

        if not torch.cuda.is_available():
            raise InvalidOptionError(f"{spelled('sr.device')}: cuda: no CUDA device is available (use cpu)")
    from tiledsm.io import open_scene
    from tiledsm.sr.infer import super_resolve  # imports torch: after the cheap checks

    scene = open_scene(src, chunks=spec.chunk)
    if spec.bit_depth is not None:
        scene.attrs["bit_depth"] = spec.bit_depth
    plan.inputs.append(InputInfo(image, src, f"{scene.sizes['y']} x {scene.sizes['x']} px, "
                                             f"camera: {scene.attrs.get('camera_source', '?')}"))
    if spec.weights:
        from tiledsm.sr.registry import load_weights

        weights = existing_file(spec.weights, spelled("sr.weights"))
        plan.inputs.append(InputInfo(spelled("sr.weights"), weights))
        net = load_weights(weights, spec.device)
    else:
        from tiledsm.sr.registry import weight_chain

        if weight_chain(spec.model, spec.scale) is None:  # neither native weights nor x2 weights to apply repeatedly
            check_sr_weights([spec.model], spec.scale, spelled("sr.scale"),
                             f"pass {spelled('sr.weights')} FILE (see `tiledsm train-sr`), a power-of-two scale "
                             f"or {spelled('sr.model')} bicubic")
        net = spec.model
    plan.product = hr = super_resolve(scene, net, spec.scale, device=spec.device, blur_sigma=spec.blur_sigma,
                                      noise=spec.noise, normalisation=spec.normalisation)
    if hr.attrs.get("sr_scheme"):
        plan.warn(f"{spec.model} has no native x{spec.scale} weights: its {hr.attrs['sr_scheme']} (a substitute, "
                  "recorded in the output's sr_scheme tag)")
    ny, nx = hr.sizes["y"], hr.sizes["x"]
    nby, nbx = -(-scene.sizes["y"] // spec.chunk), -(-scene.sizes["x"] // spec.chunk)
    plan.grid = (f"{ny} x {nx} px output (x{spec.scale}) in {product_name(recipe)}, tiles of {spec.chunk} input px: "
                 f"{nby} x {nbx} = {nby * nbx}")
    plan.tasks = len(hr.data.__dask_graph__())
    plan.notes.append("memory per worker is not estimated for SR")
    check_earlier_run(recipe, plan.out, overwrite, "OUT" if plan.command == "sr" else "--out")
    product = plan.out / product_name(recipe)
    plan.reuse = (f"nothing: {product.name} is written whole, atomically" +
                  (" (replacing the one of the same recipe there)" if product.exists() else ""))
    return plan


def check_sr_weights(models: Sequence[str], scale: int, scale_name: str, remedy: str) -> None:
    """Refuse an SR scale for which a requested network has no shipped
    weights; the message names ``scale_name`` and ends with ``remedy``
    (what to do instead, in the caller's options)."""
    from tiledsm.sr.registry import MODELS, WEIGHTLESS, available_weights, weights_path

    missing = [m for m in models if m in MODELS and m not in WEIGHTLESS and not weights_path(m, scale).exists()]
    if missing:
        have = ", ".join(f"{n} x{s}" for n, s in available_weights()) or "none"
        raise InvalidOptionError(
            f"{scale_name} {scale}: no shipped weights for {', '.join(missing)} at x{scale} (shipped: {have}); {remedy}"
        )

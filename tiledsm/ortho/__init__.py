"""Orthoimages: interpolation kernels (NN/BL/CR/CS), tiled orthorectification
of any image (RPC or frame camera) on a DSM, with occlusion.

Public API: :data:`KERNELS`, :func:`get_kernel`, :func:`sample` (kernels);
:func:`orthorectify` (:mod:`tiledsm.ortho.rectify`), its parameters
:class:`~tiledsm.ortho.recipe.OrthoSpec` (the recipe's ``ortho:`` section).

The stage (``pipeline: ortho``, ``tiledsm ortho``): its recipe
(:mod:`tiledsm.ortho.recipe`), its plan (:mod:`tiledsm.ortho.plan`), its
runner (:mod:`tiledsm.ortho.run`) and its products
(:mod:`tiledsm.ortho.stage`).
"""

from tiledsm.ortho.kernels import KERNELS, Kernel, get_kernel, register_kernel, sample

__all__ = ["KERNELS", "Kernel", "get_kernel", "register_kernel", "sample"]

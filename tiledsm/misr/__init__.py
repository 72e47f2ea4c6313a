"""Multi-image super-resolution of orthoimages (UAV): SR-S, SR-R, SR-O.

- :mod:`tiledsm.misr.register`: sub-pixel registration of an ortho to a
  reference ortho (OpenCV's ECC) and grey-level adjustment;
- :mod:`tiledsm.misr.ibp`: iterative back projection (Irani & Peleg 1993),
  tiled over the HR grid, one ``map_overlap``-style pass per iteration;
- :mod:`tiledsm.misr.methods`: the three methods and radial selection;
- :mod:`tiledsm.misr.metrics`: PSNR/SSIM against truth and the resolving
  power on a stripe chart.
"""

from tiledsm.misr.methods import MISRError, SRInputs, radial_select, reference_index, sr_o, sr_r, sr_s
from tiledsm.misr.metrics import resolved_px, stripe_contrast

__all__ = ["MISRError", "SRInputs", "radial_select", "reference_index", "sr_s", "sr_r", "sr_o", "resolved_px",
           "stripe_contrast"]

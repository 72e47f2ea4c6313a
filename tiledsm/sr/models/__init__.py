"""SR networks, one per file. Importing this package registers them in
:data:`tiledsm.sr.registry.MODELS` (explicit imports, no folder scanning)."""

from tiledsm.sr.models.base import SRModel
from tiledsm.sr.models.bicubic import Bicubic
from tiledsm.sr.models.srcnn import SRCNN
from tiledsm.sr.models.srmd import SRMD
from tiledsm.sr.models.srmd_official import OfficialSRMD
from tiledsm.sr.models.vdsr import VDSR

__all__ = ["SRModel", "Bicubic", "SRCNN", "VDSR", "SRMD", "OfficialSRMD"]

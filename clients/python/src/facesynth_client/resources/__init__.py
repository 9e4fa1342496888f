"""The API's resources, one module each; a client holds one instance of each
(``client.actors``, ``client.clips``, ...), shared by :class:`~facesynth_client.Client` and
:class:`~facesynth_client.AsyncClient`."""

from .actors import Actors
from .artifacts import Artifacts
from .bone_rigs import BoneRigs
from .clips import Clips
from .jobs import Jobs
from .models import Models
from .rigs import Rigs
from .scans import Scans
from .synthesis import Synthesis
from .tracking import Tracking

__all__ = ["Actors", "Artifacts", "BoneRigs", "Clips", "Jobs", "Models", "Rigs", "Scans", "Synthesis", "Tracking"]

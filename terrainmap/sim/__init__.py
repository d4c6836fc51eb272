"""Stereo simulator of off-road drives with ground truth (the paper's missing "simulator").

A stereo camera on a vehicle drives over procedural terrain (scenes after the paper's Fig. 7:
``flat``, ``hills``, ``ditch``, ``mounds``, ``canyon``, ``climb``) with obstacles standing on it
(pedestrians, some walking; cars; trucks; rocks; poles; a low wide mound). Images are rendered by
ray casting the height field and the obstacle solids in vectorised numpy, and written as a log
exactly like a real robot's, plus the truth the renderer used:

- :mod:`.scenes` terrain shapes and obstacle placement; :mod:`.heightfield` the terrain height
  function; :mod:`.obstacles` solids and their ray intersection; :mod:`.noise` value noise.
- :mod:`.rig` camera intrinsics, mounting and the terrain-following vehicle pose.
- :mod:`.raycast` the ray caster; :mod:`.shading` textures, light, sky and sensor effects;
  :mod:`.render` one frame.
- :mod:`.mcap_log` the ROS 2 MCAP layout (topics listed there) and :mod:`.folder_log` the folder
  layout; :mod:`.messages` the ROS messages both ways.
- :mod:`.truth` :func:`open_truth`, the reader the accuracy evaluation uses.
- :mod:`.simulate` :class:`SimConfig` and :func:`simulate`, what ``terrainmap simulate`` calls.

Conventions: world frame ``odom`` (z up, z = 0 the terrain's datum; the vehicle starts on the
terrain at x = y = 0 heading along +x), ``base_link`` on the ground under the camera, camera
optical frames per REP-103; depth is the distance along the left camera's optical axis (REP 118
``32FC1``, +inf for sky); label 0 sky, 1 terrain, 2 obstacle (the values of
:class:`terrainmap.types.Label`). A log is a pure function of its :class:`SimConfig` (seed
included): same config, same bytes of image and truth data.
"""

from .scenes import SCENES
from .simulate import SimConfig, simulate
from .truth import Truth, TruthFrame, open_truth

__all__ = ["SCENES", "SimConfig", "Truth", "TruthFrame", "open_truth", "simulate"]

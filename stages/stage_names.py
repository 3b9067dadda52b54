"""The stages' names in the registry's order, without importing the stages (torch, open3d): the command line
offers them as choices for every command, and most commands need no stage (``ultrastage simulate`` starts 2 s
sooner). :mod:`stages.registry` checks at import that its classes carry these names in this order."""
from __future__ import annotations

STAGE_NAMES: tuple[str, ...] = ("cameras", "colour", "lights", "plates", "decode", "photometric", "geometry",
                                "textures", "materials", "diffuse_normals", "relight", "relightset", "exports")

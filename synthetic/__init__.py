"""Light-stage simulator: renders raw captures (DNG) + ground truth of a subject on the UltraStage rig.

    from synthetic import SimConfig, simulate
    simulate(Path("capture"), SimConfig(actions=2, width=320))
"""
from .config import SimConfig
from .simulate import simulate

__all__ = ["SimConfig", "simulate"]

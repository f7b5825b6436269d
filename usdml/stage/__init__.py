"""The scene delegate: reads USD stages into :mod:`usdml.scene` snapshots."""

from usdml.stage.delegate import StageDelegate, open_stage

__all__ = ["StageDelegate", "open_stage"]

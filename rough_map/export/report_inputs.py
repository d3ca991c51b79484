"""What the report reads: the analysis of a traverse, as a Protocol, and extra tables.

The export layer sits below :mod:`rough_map.workflow`, so the report does not import
:class:`rough_map.workflow.TraverseAnalysis`; it names what it reads of it here
(:class:`AnalysisResult`), with the concrete types of the layers below (the feature table,
the map, the extraction spec) and small protocols for the traverse and the prediction.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from rough_map.features import FeatureTable
from rough_map.map.grid import GridMap
from rough_map.patch import Extraction

__all__ = ["AnalysisResult", "PredictionLike", "ReportTable", "TraverseLike"]


@dataclass
class ReportTable:
    """A table for the report (e.g. the demo's synthetic-patch and stereo tables).

    Attributes
    ----------
    title : str
        Heading above the table.
    head : list of str
        Column names (with units, e.g. ``"R [m³/rad]"``).
    rows : list of list
        Cells; floats are shown with 3 decimals, NaN as a dash.
    caption : str
        What the table shows, under the heading.
    notes : list of str
        Lines under the table (e.g. a timing).
    """

    title: str
    head: list[str]
    rows: list[list[Any]]
    caption: str = ""
    notes: list[str] = field(default_factory=list)


class TraverseLike(Protocol):
    """A traverse (:class:`rough_map.io.traverse.Traverse`): name, frames, clouds."""

    @property
    def name(self) -> str: ...

    @property
    def frames(self) -> Sequence[Any]:
        """Frames with an ``imu`` (roll, pitch in rad) or None."""
        ...

    def load_cloud(self, index: int) -> np.ndarray:
        """Points (N, 3) in m in the vehicle frame of frame ``index``."""
        ...


class PredictionLike(Protocol):
    """Per-frame classes (:class:`rough_map.classify.TerrainPrediction`)."""

    @property
    def filtered_class(self) -> np.ndarray: ...

    @property
    def defect(self) -> np.ndarray | None: ...

    @property
    def novelty(self) -> np.ndarray | None: ...

    @property
    def mode(self) -> str: ...


class AnalysisResult(Protocol):
    """The analysis of a traverse (:class:`rough_map.workflow.TraverseAnalysis`)."""

    @property
    def traverse(self) -> TraverseLike: ...

    @property
    def features(self) -> FeatureTable: ...

    @property
    def prediction(self) -> PredictionLike | None: ...

    @property
    def map(self) -> GridMap: ...

    @property
    def model(self) -> object | None: ...

    @property
    def extraction(self) -> Extraction:
        """The patch and estimator options the features were computed with."""
        ...

    @property
    def far_report(self) -> Mapping[str, Any]:
        """Near-to-far areas (m²) and accuracy by distance; empty without near-to-far."""
        ...

    def truth_accuracy(self) -> Mapping[str, float]:
        """``near_class_accuracy`` / ``far_class_accuracy`` against the simulator's truth."""
        ...

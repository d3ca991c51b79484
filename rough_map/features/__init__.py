"""Features along a traverse: for every frame, the patch ahead and its PSD roughness.

:func:`traverse_features` is the one place that turns a traverse into a
:class:`FeatureTable` (one row per frame with the columns of :data:`COLUMNS`, plus the
patch-mean log10 PSD ``psd_01`` ... that the classifier uses), given a
:class:`rough_map.patch.Extraction`; :func:`feature_tables` computes or reads the tables of
several traverses.

* :mod:`rough_map.features.table`: :class:`FeatureTable`, its columns and units, and
  :func:`label_summary` (R and w by label);
* :mod:`rough_map.features.extract`: :func:`cloud_roughness` and :func:`frame_features`
  (one cloud);
* :mod:`rough_map.features.frames`: one pass over a traverse's frames, each cloud read once,
  on several processes (:func:`iter_frames`);
* :mod:`rough_map.features.traverse`: :func:`traverse_features`, :func:`feature_tables`,
  and :func:`resolve_spacing`, the one grid step of a traverse with ``spacing: auto``;
* :mod:`rough_map.features.files`: :func:`write_features` / :func:`read_features` (plain
  CSV with its JSON metadata beside it, or Parquet).
"""

from rough_map.features.extract import cloud_roughness, frame_features, inconsistency
from rough_map.features.files import (
    FEATURES_FORMAT,
    FEATURES_FORMAT_VERSION,
    features_metadata,
    features_metadata_path,
    read_features,
    write_features,
)
from rough_map.features.frames import (
    SOURCES,
    FrameJob,
    FrameOutput,
    FramePass,
    FrameStream,
    HeightSample,
    frame_jobs,
    iter_frames,
)
from rough_map.features.table import (
    COLUMN_UNITS,
    COLUMNS,
    FeatureTable,
    LabelSummary,
    label_summary,
)
from rough_map.features.traverse import feature_tables, resolve_spacing, traverse_features

__all__ = [
    "COLUMNS",
    "COLUMN_UNITS",
    "FEATURES_FORMAT",
    "FEATURES_FORMAT_VERSION",
    "SOURCES",
    "FeatureTable",
    "FrameJob",
    "FrameOutput",
    "FramePass",
    "FrameStream",
    "HeightSample",
    "LabelSummary",
    "cloud_roughness",
    "feature_tables",
    "features_metadata",
    "features_metadata_path",
    "frame_features",
    "frame_jobs",
    "inconsistency",
    "iter_frames",
    "label_summary",
    "read_features",
    "resolve_spacing",
    "traverse_features",
    "write_features",
]

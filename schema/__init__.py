"""The contract of bssrdf-db: simulation specs (pydantic), stored-table schemas (Arrow), metadata.

No torch and no web framework here: workers, the service and clients all import this package.

>>> from schema import load_spec
>>> spec = load_spec("examples/skimmilk.json")        # doctest: +SKIP
>>> [c.albedo for c in spec.channels()]               # doctest: +SKIP

Modules: :mod:`schema.spec` (SimulationSpec), :mod:`schema.loading` (load_spec, parse_spec), :mod:`schema.medium` (MediumSpec,
ChannelOptics), :mod:`schema.presets` (Jensen et al. 2001 materials), :mod:`schema.bins`
(BinSpec, edges), :mod:`schema.tables` (Arrow schemas, metadata keys), :mod:`schema.errors`,
:mod:`schema.constraints` (range checks), :mod:`schema.names` (the name rule),
:mod:`schema.version` (code version), :mod:`schema.json_schema` (JSON Schema file),
:mod:`schema.sweep` (SweepSpec: grids of media), :mod:`schema.media` (a job's media and its task
index <-> (medium, shard)),
:mod:`schema.estimate` (what a spec costs: photons, steps, CPU seconds per shard).
"""

from .bins import (
    DEFAULT_MAX_MFP,
    MAX_TOTAL_BINS,
    BinSpec,
    CosThetaOBins,
    PhiOBins,
    RadialBins,
    ThetaSBins,
    azimuth_edges,
    pbrt_radial_edges,
    pbrt_radius_nodes,
    radial_edges,
    uniform_edges,
)
from .errors import ShardIndexError, SpecError, format_validation_error
from .json_schema import SPEC_SCHEMA_PATH, spec_json_schema_text, write_spec_json_schema
from .media import Medium
from .medium import ChannelOptics, MediumSpec
from .presets import PRESET_CHANNELS, PRESETS, Preset, get_preset
from .names import NAME_MAX, NAME_PATTERN, InvalidName, check_name
from .spec import MAX_INCIDENCE, MAX_PHOTONS, MAX_TASKS, SimulationSpec
from .loading import load_spec, parse_spec
from .sweep import AlbedoGrid, SweepPoint, SweepSpec, linear_albedos, pbrt_albedos
from .tables import (
    BINS_SCHEMA,
    COLUMN_DOCS,
    COMPONENTS,
    ESTIMATORS,
    META_RUN,
    META_SCHEMA_VERSION,
    META_SPEC,
    RADIAL_SCHEMA,
    SCHEMA_VERSION,
    SUMMARY_SCHEMA,
    TABLE_SCHEMAS,
    table_metadata,
)
from .version import code_version

__all__ = [
    # specs
    "SimulationSpec",
    "MediumSpec",
    "ChannelOptics",
    "SweepSpec",
    "AlbedoGrid",
    "SweepPoint",
    "Medium",
    "pbrt_albedos",
    "linear_albedos",
    "BinSpec",
    "RadialBins",
    "ThetaSBins",
    "CosThetaOBins",
    "PhiOBins",
    "load_spec",
    "parse_spec",
    "radial_edges",
    "uniform_edges",
    "azimuth_edges",
    "pbrt_radius_nodes",
    "pbrt_radial_edges",
    "MAX_PHOTONS",
    "MAX_INCIDENCE",
    "MAX_TASKS",
    "MAX_TOTAL_BINS",
    "DEFAULT_MAX_MFP",
    # names and provenance
    "check_name",
    "InvalidName",
    "NAME_MAX",
    "NAME_PATTERN",
    "code_version",
    # presets
    "PRESETS",
    "PRESET_CHANNELS",
    "Preset",
    "get_preset",
    # errors
    "SpecError",
    "ShardIndexError",
    "format_validation_error",
    # JSON Schema
    "SPEC_SCHEMA_PATH",
    "spec_json_schema_text",
    "write_spec_json_schema",
    # stored tables
    "SCHEMA_VERSION",
    "META_SPEC",
    "META_RUN",
    "META_SCHEMA_VERSION",
    "ESTIMATORS",
    "COMPONENTS",
    "COLUMN_DOCS",
    "RADIAL_SCHEMA",
    "BINS_SCHEMA",
    "SUMMARY_SCHEMA",
    "TABLE_SCHEMAS",
    "table_metadata",
]

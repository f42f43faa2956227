"""Simulated SAR scenes with ground truth: clutter, ships, land and sensor artefacts.

The simulator writes scenes of the scene store (docs/interfaces/files.md) (``intensity``, ``slc`` with ``hh``,
``quadpol`` with ``hh``, ``hv``, ``vv``) and a truth GeoJSON of the same schema as the
detections, for tests, demos and benchmarks of the detectors (up to 65536 px a side).

The package (formerly the single module ``simulate.py``) is split by component:

* :mod:`~sarship.pipeline.simulate.config`: :class:`SimConfig`, :func:`validate`, scene
  variables;
* :mod:`~sarship.pipeline.simulate.fields`: seeded random streams on the block grid,
  correlated Gaussian fields and the Gamma texture copula;
* :mod:`~sarship.pipeline.simulate.clutter`: sea clutter (speckle, :func:`sea_covariance`);
* :mod:`~sarship.pipeline.simulate.land`: coast and land model;
* :mod:`~sarship.pipeline.simulate.ships`: ship placement and signatures;
* :mod:`~sarship.pipeline.simulate.artefacts`: sidelobes, azimuth ambiguities, stripes, RFI;
* :mod:`~sarship.pipeline.simulate.geometry`: the simulated sensor's geometry (``sar_geometry``:
  where the azimuth ambiguities fall, line times, look directions);
* :mod:`~sarship.pipeline.simulate.motion`: moving ships (SOG, COG) and their azimuth
  displacement;
* :mod:`~sarship.pipeline.simulate.ais_vessels`: the scene's vessels as AIS knows them (MMSIs,
  dark ships, AIS-only vessels);
* :mod:`~sarship.pipeline.simulate.ais_reports`: their AIS reports and the plain AIS CSV;
* :mod:`~sarship.pipeline.simulate.model`: the per-configuration scene model;
* :mod:`~sarship.pipeline.simulate.render`: pixel rendering, :func:`simulate_tile`;
* :mod:`~sarship.pipeline.simulate.ground_truth`: :func:`ship_catalogue`, the truth GeoJSON;
* :mod:`~sarship.pipeline.simulate.run`: :func:`simulate_array` and :func:`simulate` (writes
  the scene store and its truth).

Every name of the former module that other code uses is re-exported here.
"""

# Re-exports: the public API (``__all__``) and every other name that other code or the tests
# use (``from sarship.pipeline import simulate as sim; sim.SEA_RHO, sim._model, ...``).
from sarship.pipeline.simulate.ais_reports import AisOptions, ais_reports, write_ais_csv  # noqa: F401
from sarship.pipeline.simulate.artefacts import (  # noqa: F401
    AMBIG_LEVEL_DB,
    AMBIG_SMEAR,
    SIDELOBE_FLOOR,
    SIDELOBE_MAX_PX,
    SIDELOBE_MIN,
    SIDELOBE_OS,
)
from sarship.pipeline.simulate.clutter import (  # noqa: F401
    SEA_EPS,
    SEA_GAMMA,
    SEA_RHO,
    effective_looks,  # noqa: F401
    sea_covariance,
)
from sarship.pipeline.simulate.config import (  # noqa: F401
    BORDER_PX,
    CLUTTERS,
    GAP_PX,
    KINDS,
    SimConfig,
    max_ships,
    validate,
    variables,
)
from sarship.pipeline.simulate.fields import (  # noqa: F401
    _S_TEXTURE,
    BLOCK,
    NODE_BLOCK,
    _gamma_texture,
    _gauss_field,
)
from sarship.pipeline.simulate.geometry import ghost_offsets, sar_geometry  # noqa: F401
from sarship.pipeline.simulate.ground_truth import ship_catalogue, truth_collection  # noqa: F401
from sarship.pipeline.simulate.land import (  # noqa: F401
    LAND_EPS,
    LAND_GAIN_CORR_PX,
    LAND_GAMMA,
    LAND_RHO,
    LAND_TEXTURE_CORR_PX,
    LAND_TEXTURE_NU,
    URBAN_PX_PER_POINT,
    _land_mask,
)
from sarship.pipeline.simulate.model import _model  # noqa: F401
from sarship.pipeline.simulate.render import simulate_tile  # noqa: F401
from sarship.pipeline.simulate.run import acquired_time, simulate, simulate_array  # noqa: F401
from sarship.pipeline.simulate.ships import (  # noqa: F401
    COVERAGE_MIN,
    HULL_SIGMA,
    LAND_MARGIN_PX,
    SHIP_CLASSES,
)

__all__ = [
    "SimConfig",
    "validate",
    "ship_catalogue",
    "simulate_tile",
    "truth_collection",
    "simulate_array",
    "simulate",
    "sea_covariance",
    "effective_looks",
    "variables",
    "AisOptions",
    "ais_reports",
    "write_ais_csv",
]

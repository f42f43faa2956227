"""AIS: vessel reports read from the files the field exchanges, their tracks at the scene's time,
and their matching to detections (which ships reported themselves, which are dark).

- :mod:`sarship.pipeline.ais.reports`: the shared records (:class:`Window`, :class:`Reports`,
  :class:`VesselInfo`, :class:`ReadStats`, :class:`VesselStates`);
- :mod:`sarship.pipeline.ais.formats`: NMEA 0183 (pyais), MarineCadastre, Danish Maritime
  Authority and plain CSV files, streamed through a time and space window;
- :mod:`sarship.pipeline.ais.tracks`: each vessel's position and velocity at a time;
- :mod:`sarship.pipeline.ais.displacement`: the azimuth displacement of a moving ship;
- :mod:`sarship.pipeline.ais.match`: pair scores, one global assignment, dark and unmatched.

Conventions (every module): times are POSIX seconds (UTC, float64); positions WGS84 degrees;
speeds over ground in knots as AIS gives them and metres per second inside the maths (1 kn =
1852/3600 m/s); courses and headings in degrees clockwise from true north; unknown values NaN
(AIS's own "not available" codes, e.g. SOG 102.3, COG 360, heading 511, become NaN on reading).
"""

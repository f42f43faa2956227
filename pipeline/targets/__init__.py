"""From a detection mask to ships: connected components across tiles, features and discrimination,
sidelobes, azimuth ambiguities, local contrast, chip segmentation and geolocation."""

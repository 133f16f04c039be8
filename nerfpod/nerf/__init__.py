"""Pure NeRF math: cameras and rays, sampling, encodings, fields, volume rendering."""

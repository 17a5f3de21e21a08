"""The AFM instrument: simulated, DAQ hardware or replayed; raster scans, scan lines, tip moves,
indentation."""

"""The live viewer: the graph's scene served to Foxglove by the Foxglove SDK."""

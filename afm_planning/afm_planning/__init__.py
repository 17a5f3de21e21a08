"""Landmark path planning with probability regions and push sequencing."""

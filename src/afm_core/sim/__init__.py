"""The simulated AFM instrument: sample world, tip, imaging (more physics in later work)."""

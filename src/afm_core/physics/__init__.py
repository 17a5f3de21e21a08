"""Physical models shared by the simulated instrument (afm_core.sim) and the planners and
estimators that use them as their model, importable without the simulator.

- sample: the sample's objects (spheres, rods/tubes, electrodes, pits, roughness) as heights
- pushing: contact-mode pushing along a tip path (push_along_path), built from
  contact (parameters, friction, forces, stick-slip), sphere_pushing, rod_pushing,
  collisions and push_world
- tip_morphology: imaging as grey dilation by the tip, reconstruction as erosion
"""

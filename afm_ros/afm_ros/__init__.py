"""ROS glue every node shares: topic names, QoS, message conversions, parameter declaration,
the action client, the driver's actions as a core Instrument, and the node main loop."""

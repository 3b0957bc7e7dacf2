"""`leco bench`: LeCO against vanilla Switch-NeRF and the occupancy grid on one scene, measured side
by side."""

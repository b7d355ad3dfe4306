"""The robotic charging station of Paper III: connector geometry, port and plug
detection, stereo triangulation and the port's pose (`earcore charge` runs it in the
simulated charging cell)."""

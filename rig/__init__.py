"""Camera drivers (OAK via depthai, synthetic, replay), triggers, synchronized acquisition, the capture store."""

"""The forward model: shutter codes, the sensor, units, patches, metrics, streams of captures."""

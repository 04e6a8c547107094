"""Camera drivers: GenICam (Aravis, harvesters/GenTL) and a synthetic camera. No optics here."""

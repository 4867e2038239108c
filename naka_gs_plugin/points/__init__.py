"""Point-cloud preprocessing (Naka-GS PPM) and point-set alignment."""

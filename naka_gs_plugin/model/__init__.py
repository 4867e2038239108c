"""The naka-gs model: splatfacto-derived, with gsplat on CUDA and our own rasterizer elsewhere."""

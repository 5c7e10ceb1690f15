"""Core types every stage shares: camera models, poses, the lamp map, observations, ellipses, mounting, gravity."""

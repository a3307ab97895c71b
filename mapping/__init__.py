"""mapping: an OctoMap-equivalent probabilistic octree."""

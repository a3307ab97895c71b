"""perception: images, depth and clouds -> lines, vanishing points, clouds, odometry."""

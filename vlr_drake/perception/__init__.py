"""Perception: AprilTag images, camera configuration and the tag-based POM observer."""

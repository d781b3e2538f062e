"""Curated runs in other formats: LeRobot datasets (``lerobot``), frame-aligned videos (``video``)."""

"""Rendering with Mitsuba 3: scenes from meshes, cameras and lights; reference (path-traced) images."""

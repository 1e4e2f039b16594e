"""Hosts of the post-processor: CAM systems that call trueaxis from inside (FreeCAD CAM)."""

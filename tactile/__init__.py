"""Touching: contours on the object surface and the virtual FSR tactile array pressed along them."""

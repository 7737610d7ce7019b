"""From pixels to observations: target detection in photographs and video, point tracking."""

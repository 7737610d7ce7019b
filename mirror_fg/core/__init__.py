"""numpy-only core: errors, rigid transforms, the camera model and the reflection geometry (eqs. 3-9)."""

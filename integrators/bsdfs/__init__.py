"""BSDFs Mitsuba lacks: ``phong``, the energy-normalised modified Phong BSDF."""

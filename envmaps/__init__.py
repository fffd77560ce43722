"""Environment maps for mcillum scenes and the code that makes them.

Maps follow Mitsuba's ``envmap`` convention: equirectangular (latlong), y up,
pixel (u, v) = (φ/2π, θ/π) looks along (sinφ sinθ, cosθ, −cosφ sinθ).
"""

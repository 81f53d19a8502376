"""Warp kernels (installed as ``elicit_diffrender.kernels``): grid look-ups, ray marching, skinning."""

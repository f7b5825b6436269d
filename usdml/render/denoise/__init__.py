"""Denoising (issue 53 item 4, ``--denoise``): a frame's radiance AOVs through Intel Open Image Denoise, guided by
its albedo and filtered normal (docs/denoising.md).

``params`` (the parameter rows and what they accept, a leaf), ``oidn`` (the denoiser: the check at job start,
the per-frame filter, the EXR header).
"""

"""Selective foveated supersampling with Whitted ray tracing (kim2021).

Section 4.3: every pixel is presampled at its centre, gathering the attributes of Table 1 (colour; object id,
normal, shadow count and texture existence at the primary and first secondary hit). Section 4.1: eccentricity
bands e_f, e_p, e_m, e_np (3.3, 5.5, 12.1, 30 deg) split the central region (e < e_np, supersampled) from the
periphery (one sample per pixel). Section 4.4: the pixel reusability test copies a pixel from the previous
frame when its back-projected first hit lies at the same distance and the two presampled colours pass section
3's two-step test (tau_sel from the attributes at both hits) at tau_sel x tau_reuse (at most n_reuse_max times
in a row). Sections 3 and 4.6.1: the two-step disparity test per 2x2 subpixel: geometry discordance with any
of the three neighbours selects tau_sel, then Mitchell's contrast is compared with (1.36, 1.02, 2.04) x
tau_fov(e) x tau_sel, tau_fov from two C1 quadratic Bezier segments. Section 4.6.2: problematic subpixels take
(n_f, n_p, n_m, n_np) stratified jittered samples by band, jittered afresh each frame; in every central pixel
rendered, the others take the colour interpolated from the four surrounding pixel centres (Figure 2), or with
interpolate=false the presampled colour as in Jin et al.'s selective supersampling. Section 4.7: temporal
smoothing over up to 4 back-projected earlier frames with alpha(e) piecewise linear through 0.9, 0.8, 0.7,
0.5, 0.2, 0.1 at 0, e_f, e_p, e_m, e_np, e_max.

The paper leaves open when two normals disagree; here, when their dot product is below normal_cos. Reuse also
needs the copied colour rendered at no lower class (samples per problematic subpixel) than the pixel needs
now, or a saccade copies one-sample colours into the new fovea, and where the colour was sampled may drift at
most reuse_px pixels over the chain of copies (docs/methods.md, kim21, says why). The jitter is drawn per
frame (seeded by the run's seed and the frame number), as a stratified jittered sampler draws it: so section
4.7's smoothing averages it on a still view, and a reused colour is one realisation held for up to n_reuse_max
frames, which is what reuse costs against rendering afresh (Figure 6). Section 4.7's null colour of a rejected
earlier frame is no colour: the frame drops out of both sums.

The method is split by stage, each module citing its section: params (the options), bands (4.1's bands with
tau_fov of 4.6.1 and alpha of 4.7), reuse (4.3's presample attributes and 4.4's reusability test), disparity (the
two-step test of 3 and 4.6.1), supersample (4.6.2's extra samples and Figure 2's resolve), and method (the Kim21
class that runs them in order, with 4.7's smoothing).
"""

from hmdrt.foveation.kim21.bands import alpha_knots, alpha_of_eccentricity, bezier_controls, tau_fov, tau_fov_array
from hmdrt.foveation.kim21.method import Kim21
from hmdrt.foveation.kim21.params import Kim21Params

__all__ = [
    "Kim21",
    "Kim21Params",
    "alpha_knots",
    "alpha_of_eccentricity",
    "bezier_controls",
    "tau_fov",
    "tau_fov_array",
]

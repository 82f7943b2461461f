"""Foveated real-time ray tracing with reprojection (weier2016).

Section 3.1: pixels are traced when xi_q < p(q), the foveal function of the foveal region configuration (r0, r1,
p_min), and so are the support image's pixels, a regular subset of the pixels (256 x 318 at DK2's 1182 x 1464,
scaled with the profile; column floor((i + 0.5) w / sw)), one ray each, every frame. Section 3.2: the previous
final colour and cache info are reprojected through a coarse mesh built from the previous support G-buffer (its
vertices on the support pixels' centres, unprojected with the previous camera, projected with the current one),
filtering each pixel's footprint. Section 3.3: the resampling info renders that reprojection at the support
resolution and marks cells whose depth departs from their direct neighbourhood (a second difference of 1/z above
eps_depth), whose luminance contrast to a neighbour exceeds eps_lum, or whose previous surface is seen at a grazing
angle (edge_t = max(n.d, 0) < eps_edge); their pixels are traced. It tests a cell only where the reprojected image
may be wrong: where the reprojection moved the cell or a neighbour by more than eps_motion pixels, or where it
shows the support image's reconstruction of pixels that hold no sample yet; a still view reprojects the previous
frame onto itself, with nothing to find. Pixels the mesh does not cover are not marked: they are reconstructed
from the support image unless the foveal function traces them. Section 3.4: samples (the support pixels' too) in
the fovea, in resampled cells, where nothing was reprojected, or whose depth disagrees with the cache by more than
eps_cache, replace the cache; the others update it with the running estimate (alpha, rho) bounded below by k(dt)
between k_min and k_max over t_max frames. The support image and G-buffer are extracted from the support pixels'
samples; pixels left without colour are merged from the support image, colour and light buffer. Section 3.5: when
the scene has area lights or ambient occlusion, a resampled pixel outside the fovea takes the accumulated light
buffer of the closest reconstructed pixel found by n random taps in a window sized by the nearest one along the
image axes; a reconstructed pixel is one traced this frame and merged into its cache, on the pixel's surface. The
filter changes the image shown, not the cache.

Each frame reprojects the mesh, marks the resampling info, selects and traces the samples, then runs
one pass that gathers the previous frame through the mesh, applies the running estimate and merges,
reading one of two persistent final buffers per eye and writing the other and the caller's image;
nothing of the image's size is allocated per frame. On a still view, work that cannot change the image is
skipped: the mesh is rasterised again only when its inputs change, and where it reprojects every pixel onto
itself the pass updates the final buffers in place instead of copying the untraced pixels.

Values the paper leaves open (eps_*, k_min, k_max, t_max, footprint taps, post taps and its surface test) are
parameters with defaults chosen here. Section 3.4 prints alpha = min(alpha', k); the running estimate uses
max(alpha', k), the lower bound the text describes (see stages.temporal.running_estimate). The light buffer is
accumulated at the colour's rate (section 3.1 allows another).

The method is split by stage, each module citing its section: params (the parameters and the pixel flags),
buffers (what the stages share), selection (3.1), resample (3.2-3.3), cache (3.2, 3.4 and the merge), post
(3.5), and method (the Weier16 class that runs them in order).
"""

from hmdrt.foveation.weier16.method import Weier16
from hmdrt.foveation.weier16.params import Weier16Params, support_size

__all__ = ["Weier16", "Weier16Params", "support_size"]

"""Pure NeRF math, one topic a module, each tested against a brute-force or analytic reference.

    cameras          pinhole cameras with lens distortion: pixels -> rays, points -> pixels (NumPy)
    sampling         where along each ray the field is queried: stratified samples, box clipping, distance warps
    stepfun          step functions (edges, weights): resampling, outer bounds, the interlevel and distortion losses
    coord            NDC rays (forward-facing scenes), scene contraction (unbounded ones), ray-distance warps
    encodings        positional (Fourier) encoding, the multiresolution hash grid, spherical harmonics
    sparsecore       the hash grid's gather and scatter-add as SparseCore kernels (Pallas; v5p and v6e)
    fields           radiance fields: flax modules from points (and directions) to colour and density
    compositing      volume rendering: alpha compositing of colours and densities along rays
    regions          space cut into convex regions: each ray's segment per region, partial sums composited
    model            the NeRF model: sample, query the field(s), composite; coarse-to-fine or proposal sampling
    poses            similarity transforms that bring a capture's cameras into the field's frame
    pose_correction  per-frame SE(3) pose corrections (pose refinement)
    alignment        the similarity (Umeyama) of two camera sets: held-out cameras into the refined frame
    paths            camera paths from a capture's own cameras (spiral, ellipse)
    keyframes        camera paths through keyframes a user placed

No JAX device or backend, mesh, file or config reading here (but what Pallas itself asks of the chip a
SparseCore kernel is traced for): plain arrays and flax modules in, arrays out. The
model and its fields are handed the config's `model` section as a value; nerfpod.run.components.make_model reads
the config and the backend and builds the model.
"""

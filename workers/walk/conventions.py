"""Geometry, direction and unit conventions of the engine, written once.

Every kernel docstring refers here instead of restating these.

Units
    Lengths in mm and coefficients in 1/mm at the interface (spec, tables).  Inside the walk all
    lengths are *optical* (multiplied by the configuration's sigma_t), so one walk code serves every
    channel: a free path is s = -ln(u), the transmittance over d is exp(-d).  Tallies convert back
    with r_mm = r_optical / sigma_t and A_mm = A_optical / sigma_t**2.

Geometry
    The medium fills z < 0; the surface is z = 0 with outward normal n = +z.  Outside index 1,
    medium index eta (relative index; eta < 1 is allowed).  Light enters at the origin.

Directions
    A direction u = (ux, uy, uz) is the direction of travel.  Inside the medium uz < 0 goes
    deeper.  The incident ray travels along (sin theta_i, 0, -cos theta_i) (incidence in the x-z
    plane) and refracts by Snell's law.  A photon reaching the surface from inside has uz > 0; its
    internal cosine with the normal is uz.  The Fresnel reflectance at that crossing is
    Fr(uz, 1/eta); the transmitted direction is (eta ux, eta uy, sqrt(1 - eta^2 (1 - uz^2))).

Angles of a bin
    theta_s: azimuth of the exit point from +x (counterclockwise seen from +z); 0 at r = 0.
    theta_o: outgoing angle (outside the medium) from n; bins uniform in cos(theta_o) over [0, 1].
    phi_o:   azimuth of the outgoing direction measured from the outward radial direction at the
             exit point (from +x at r = 0), counterclockwise seen from +z; 0 for a direction
             straight up (no horizontal part).
    Both are binned from the vectors, not from angles: a direction's bin is decided by the signs
    of its cross products with the bins' edge directions (workers.walk.binning.sector_index).

Azimuth bins are centred on the plane of incidence
    With n bins of width h = 2 pi / n, theta_s bin k and phi_o bin k are
    [(k - 1/2) h, (k + 1/2) h) modulo 2 pi; the stored edges run from -h/2 to 2 pi - h/2
    (schema.bins.azimuth_edges, workers.walk.binning.azimuth_index and sector_index).  Bin 0
    holds theta_s = 0 (straight ahead along +x) and phi_o = 0 (leaving radially); for even n
    bin n/2 holds pi.
    Why: the problem is mirror-symmetric about the plane of incidence (y -> -y maps theta_s to
    -theta_s and phi_o to -phi_o), so S(r, theta_s, cos, phi_o) = S(r, -theta_s, cos, -phi_o),
    and with centred bins the mirror of bin (k, m) is the bin ((n_t - k) mod n_t, (n_p - m) mod n_p)
    of the same table.  Single scattering at normal incidence leaves exactly at phi_o = 0 (the
    scattering vertex is on the axis below the entry point); bins with an edge at 0 put all of
    it on one side of that edge and none in the mirror bin.

Grazing bins at eta = 1
    The exit tally scores S = w / cos(theta_o); at eta = 1 its second moment is infinite in the
    lowest cos(theta_o) bin, so those rows of bins.parquet (exits: every component; hybrid:
    multiple and total) carry S_infinite_variance = 1 and a NaN S_stderr; S itself is unbiased
    (workers.fold.output.s_infinite_variance, workers.walk.harvest).

Components
    0 = ``single`` (exactly one scattering event before leaving), 1 = ``multiple`` (two or more);
    ``total`` is their sum, formed per photon (or per batch) before squaring, so its error bar
    keeps the covariance (workers.fold.tally).

Random numbers
    Philox-4x32-10 (:mod:`workers.walk.rng`), counter (photon low, photon high, draw, purpose), key from
    (seed, configuration).  Purpose 0 with draw 0 starts the photon's walk stream (a xoshiro128+
    state carried in its lane, four outputs per step: free path, decision, cos(theta), phi);
    purposes >= 1 are the connection samples at a vertex.
"""

TALLIED_COMPONENTS = ("single", "multiple")
"""Components the tallies hold, in array order; ``total`` (schema.COMPONENTS) is their sum."""

PURPOSE_WALK = 0
PURPOSE_CONNECT = 1
"""Counter word c3: 0 for walk steps, 1 + k for the k-th block of connection samples."""
PURPOSE_ROULETTE = 0x7FFFFFFF
"""Counter word c3 of a path-length roulette round (workers.walk.path_roulette; c2 = the step count at
the round): above any connection block's 1 + k."""

__all__ = ["TALLIED_COMPONENTS", "PURPOSE_WALK", "PURPOSE_CONNECT", "PURPOSE_ROULETTE"]

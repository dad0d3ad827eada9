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
    theta_s: azimuth of the exit point from +x, in [0, 2 pi).
    theta_o: outgoing angle (outside the medium) from n; bins uniform in cos(theta_o) over [0, 1].
    phi_o:   azimuth of the outgoing direction measured from the outward radial direction at the
             exit point (from +x at r = 0), wrapped into [0, 2 pi).

Components
    0 = ``single`` (exactly one scattering event before leaving), 1 = ``multiple`` (two or more);
    ``total`` is their sum, formed per photon (or per batch) before squaring, so its error bar
    keeps the covariance (workers.tally).

Random numbers
    Philox-4x32-10 (:mod:`workers.rng`), counter (photon low, photon high, draw, purpose), key from
    (seed, configuration).  Purpose 0 is the walk step (one block of four uniforms per step:
    free path, decision, cos(theta), phi); purposes >= 1 are the connection samples at a vertex.
"""

COMPONENTS = ("single", "multiple")
"""Tallied components, in array order; ``total`` is derived."""

PURPOSE_WALK = 0
PURPOSE_CONNECT = 1
"""Counter word c3: 0 for walk steps, 1 + k for the k-th block of connection samples."""

__all__ = ["COMPONENTS", "PURPOSE_WALK", "PURPOSE_CONNECT"]

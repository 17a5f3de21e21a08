"""Contact-mode pushing against closed forms and physical expectations.

Expected values are derived here from the geometry and the mechanics (closed forms, or an
independent numerical minimisation / integration), never taken from the code under test.
"""

import math
import time

import numpy as np
import pytest
from scipy.integrate import trapezoid  # numpy < 2 (the Docker image's) has no np.trapezoid
from scipy.optimize import brentq, minimize, minimize_scalar

from afm_core.physics.contact import ContactParams
from afm_core.physics.pushing import push_along_path
from afm_core.physics.rod_pushing import rod_end_twists
from afm_core.physics.sample import Electrode, Rod, Sample, Sphere

nm = 1e-9
R_T = 50 * nm  # the book's effective tip contact radius
R_P = 100 * nm  # the book's particle radius
D = R_T + R_P  # centre distance at contact (planar model)
DT = 1e-3


def line(x0, y0, x1, y1, n):
    t = np.linspace(0.0, 1.0, n)
    return x0 + (x1 - x0) * t, y0 + (y1 - y0) * t


def frictionless(**kw):
    return ContactParams(mu_tip_particle=0.0, **kw)


# ---------------------------------------------------------------------------- spheres


@pytest.mark.parametrize("heading_deg", [0.0, 37.0, -120.0])
def test_centre_push_moves_the_sphere_straight_by_the_travel_past_first_contact(heading_deg):
    ux, uy = math.cos(math.radians(heading_deg)), math.sin(math.radians(heading_deg))
    cx, cy = 1.3e-6, -0.4e-6
    sample = Sample(spheres=[Sphere(7, cx, cy, R_P)])
    start, end = -400 * nm, 250 * nm  # along u, relative to the sphere's centre
    px, py = line(cx + start * ux, cy + start * uy, cx + end * ux, cy + end * uy, 6501)
    result = push_along_path(sample, px, py, DT, ContactParams())
    travel_past_contact = end - (-D)  # first contact when the tip is D before the centre
    s = sample.spheres[0]
    assert s.x == pytest.approx(cx + travel_past_contact * ux, abs=1e-12)
    assert s.y == pytest.approx(cy + travel_past_contact * uy, abs=1e-12)
    assert math.hypot(s.x - px[-1], s.y - py[-1]) == pytest.approx(D, abs=1e-12)  # ends in contact
    assert result.moved_ids == [7]


def test_a_path_beside_the_particle_moves_nothing_and_feels_only_substrate_friction():
    params = ContactParams()
    sample = Sample(spheres=[Sphere(0, 0.0, D + 1 * nm, R_P), Sphere(1, 0.0, -(D + 1 * nm), R_P)])
    px, py = line(-500 * nm, 0.0, 500 * nm, 0.0, 4001)
    result = push_along_path(sample, px, py, DT, params)
    assert result.moved_ids == []
    assert [(s.x, s.y) for s in sample.spheres] == [(0.0, D + 1 * nm), (0.0, -(D + 1 * nm))]
    sliding = params.mu_tip_substrate * params.normal_force
    np.testing.assert_allclose(result.lateral_force, sliding, rtol=1e-12)
    np.testing.assert_allclose(
        result.lateral_torsion,
        sliding * params.tip_height / params.lateral_spring_constant,
        rtol=1e-12,
    )


def frictionless_off_centre(offset, travel):
    """Closed form for a particle that moves along the contact normal (no tip friction):
    with theta the normal's angle from the push direction, D dtheta = sin(theta) dx_tip
    and the particle moves dx_tip cos(theta) along the normal, so after `travel` past first
    contact tan(theta/2) = tan(theta0/2) exp(travel / D), dx = travel + D (cos theta -
    cos theta0), dy = D (sin theta - sin theta0), theta0 = asin(offset / D)."""
    th0 = math.asin(offset / D)
    th = min(2 * math.atan(math.tan(th0 / 2) * math.exp(travel / D)), math.pi / 2)
    travel = min(
        travel, D * math.log(math.tan(math.pi / 4) / math.tan(th0 / 2))
    )  # contact lost at 90 deg
    return travel + D * (math.cos(th) - math.cos(th0)), D * (math.sin(th) - math.sin(th0))


@pytest.mark.parametrize("side", [1.0, -1.0])
def test_off_centre_push_without_tip_friction_moves_the_particle_along_the_contact_normal(side):
    offset = side * 60 * nm
    x_contact = -math.sqrt(D**2 - offset**2)
    # a short push: the displacement points along the normal at first contact
    sample = Sample(spheres=[Sphere(0, 0.0, offset, R_P)])
    px, py = line(-400 * nm, 0.0, x_contact + 0.5 * nm, 0.0, 4001)
    push_along_path(sample, px, py, DT, frictionless())
    s = sample.spheres[0]
    direction = math.atan2(s.y - offset, s.x)
    assert direction == pytest.approx(math.asin(offset / D), abs=math.radians(0.1))
    assert np.sign(s.y - offset) == side  # deflected to the side it was hit on
    # partway and all the way through: the closed-form trajectory
    for end in (x_contact + 40 * nm, 1500 * nm):
        sample = Sample(spheres=[Sphere(0, 0.0, offset, R_P)])
        px, py = line(-400 * nm, 0.0, end, 0.0, 19001)
        push_along_path(sample, px, py, DT, frictionless())
        dx, dy = frictionless_off_centre(abs(offset), end - x_contact)
        s = sample.spheres[0]
        assert s.x == pytest.approx(dx, abs=0.2 * nm)
        assert s.y - offset == pytest.approx(side * dy, abs=0.2 * nm)
    assert abs(s.y) == pytest.approx(D, abs=0.2 * nm)  # slid off: ends tangent to the path


def disc_patch_friction(rho, n=300):
    """Force and torque (units F_c, F_c a) of a uniformly pressed disc spinning about a point
    rho radii from its centre: brute-force midpoint sum over the disc."""
    r = (np.arange(n) + 0.5) / n
    th = (np.arange(2 * n) + 0.5) * np.pi / n
    rr, tt = np.meshgrid(r, th)
    x, y = rr * np.cos(tt), rr * np.sin(tt)
    w = rr / n * (np.pi / n) / np.pi
    d = np.hypot(x, y + rho)
    return np.sum(w * (y + rho) / d), np.sum(w * (x * x + y * (y + rho)) / d)


def expected_deflection(alpha, a, mu):
    """Angle beta between the contact normal and the particle's motion, from force and torque
    balance with a sticking tip contact (see the module docstring), capped by sliding."""
    eps = a / R_P

    def torque_balance(beta):
        rho = 1 / (eps * math.cos(beta) * (math.tan(alpha) - math.tan(beta)))
        f, m = disc_patch_friction(rho)
        return math.sin(beta) * f - eps * m

    return min(brentq(torque_balance, 1e-9, alpha - 1e-9, xtol=1e-10), math.atan(mu))


@pytest.mark.parametrize("a, mu", [(80 * nm, 1.0), (80 * nm, 0.02)])
def test_spin_friction_turns_the_particle_from_the_normal_towards_the_push(a, mu):
    offset = 60 * nm
    theta0 = math.asin(offset / D)
    beta = expected_deflection(theta0, a, mu)
    assert math.radians(1) < beta < theta0 - math.radians(1)  # the case is informative
    sample = Sample(spheres=[Sphere(0, 0.0, offset, R_P)])
    px, py = line(-300 * nm, 0.0, -math.sqrt(D**2 - offset**2) + 0.5 * nm, 0.0, 3001)
    push_along_path(
        sample, px, py, DT, ContactParams(substrate_contact_radius=a, mu_tip_particle=mu)
    )
    s = sample.spheres[0]
    assert math.atan2(s.y - offset, s.x) == pytest.approx(theta0 - beta, abs=math.radians(0.1))


def test_a_push_through_a_slightly_missed_centre_is_unstable():
    """SPEC 5: with the default (small) contact patch the particle slides off to the side."""
    for offset in (3 * nm, -3 * nm):
        sample = Sample(spheres=[Sphere(0, 0.0, offset, R_P)])
        px, py = line(-300 * nm, 0.0, 3000 * nm, 0.0, 20001)
        push_along_path(sample, px, py, DT, ContactParams())
        s = sample.spheres[0]
        assert np.sign(s.y) == np.sign(offset)
        assert abs(s.y) == pytest.approx(D, abs=0.5 * nm)  # left beside the path
        assert s.x < 1500 * nm  # not carried to the end


def test_sparse_path_samples_do_not_tunnel_through_a_particle():
    dense = Sample(spheres=[Sphere(0, 0.0, 0.0, R_P)])
    sparse = Sample(spheres=[Sphere(0, 0.0, 0.0, R_P)])
    push_along_path(dense, *line(-400 * nm, 0.0, 400 * nm, 0.0, 8001), DT, ContactParams())
    push_along_path(
        sparse, np.array([-400 * nm, 400 * nm]), np.array([0.0, 0.0]), DT, ContactParams()
    )
    assert sparse.spheres[0].x == pytest.approx(400 * nm + D, abs=1e-12)
    assert sparse.spheres[0].x == pytest.approx(dense.spheres[0].x, abs=1e-12)


# ---------------------------------------------------------------------------- rods


def rod_pose_after(rod, px, py, params):
    sample = Sample(rods=[rod])
    push_along_path(sample, px, py, DT, params)
    return sample.rods[0]


@pytest.mark.parametrize("angle_deg", [0.0, 30.0])
def test_rod_pushed_at_its_centre_translates_without_rotating(angle_deg):
    L, r, ang = 1000 * nm, 20 * nm, math.radians(angle_deg)
    nx, ny = -math.sin(ang), math.cos(ang)  # push across the axis
    cx, cy = 0.2e-6, 0.1e-6
    start, end = -300 * nm, 100 * nm
    px, py = line(cx + start * nx, cy + start * ny, cx + end * nx, cy + end * ny, 4001)
    rod = rod_pose_after(Rod(3, cx, cy, ang, L, r), px, py, ContactParams())
    travel = end - (-(R_T + r))
    assert rod.angle == pytest.approx(ang, abs=1e-12)
    assert rod.x == pytest.approx(cx + travel * nx, abs=1e-12)
    assert rod.y == pytest.approx(cy + travel * ny, abs=1e-12)


def min_work_irc(s_c, L):
    """IRC on the axis minimising the friction work per unit contact displacement for uniform
    Coulomb friction: integral |s - x0| ds / |s_c - x0|, by numerical quadrature."""
    if s_c < 0:
        return -min_work_irc(-s_c, L)
    s = np.linspace(-L / 2, L / 2, 20001)

    def work(x0):
        return trapezoid(np.abs(s - x0), s) / abs(s_c - x0)

    return minimize_scalar(
        work, bounds=(-L / 2, s_c - 1e-3 * L), method="bounded", options={"xatol": 1e-6 * L}
    ).x


@pytest.mark.parametrize("s_c", [400 * nm, -300 * nm])
def test_rod_pushed_near_an_end_rotates_about_a_pivot_towards_the_far_end(s_c):
    L, r = 1000 * nm, 20 * nm
    push = 5 * nm  # past first contact
    params = ContactParams(rod_contact_halfwidth=0.0)
    px, py = line(s_c, -300 * nm, s_c, -(R_T + r) + push, 3001)
    rod = rod_pose_after(Rod(0, 0.0, 0.0, 0.0, L, r), px, py, params)
    x0 = min_work_irc(s_c, L)
    assert np.sign(x0) == -np.sign(s_c) and abs(x0) > 0.2 * L  # the pivot is on the far half
    dtheta = rod.angle
    assert np.sign(dtheta) == np.sign(s_c)  # +y push right of centre turns it CCW
    assert dtheta == pytest.approx(push / (s_c - x0), rel=0.01)
    # the fixed point of the rigid motion (initial centre at the origin, angle 0)
    c, s = math.cos(dtheta), math.sin(dtheta)
    pivot = np.linalg.solve(np.array([[1 - c, s], [-s, 1 - c]]), np.array([rod.x, rod.y]))
    assert pivot[0] == pytest.approx(x0, abs=2 * nm)
    assert abs(pivot[1]) < 2 * nm


def test_rod_pushed_on_its_end_cap_along_its_axis_slides_lengthwise():
    L, r = 600 * nm, 15 * nm
    px, py = line(-700 * nm, 0.0, -200 * nm, 0.0, 3001)
    rod = rod_pose_after(Rod(0, 0.0, 0.0, 0.0, L, r), px, py, ContactParams())
    assert rod.angle == pytest.approx(0.0, abs=1e-12)
    assert rod.y == pytest.approx(0.0, abs=1e-12)
    assert rod.x == pytest.approx(-200 * nm + R_T + r + L / 2, abs=1e-12)


@pytest.mark.parametrize("psi_deg", [20.0, 44.0, 70.0, 90.0])
def test_end_cap_twists_minimise_the_friction_work(psi_deg):
    """Independent check of the tabulated end-cap law: minimise the quadrature of |v(s)|
    over all twists that move the end point s = 1/2 by one unit along the normal."""
    psi = math.radians(psi_deg)
    table = rod_end_twists()
    k = int(psi_deg) // 2  # the table runs 0..90 deg in 2 deg steps
    n = np.array([-math.cos(psi), math.sin(psi)])
    s = np.linspace(-0.5, 0.5, 4001)

    def work(z):  # z = (vx, omega): vy from the constraint
        vx, w = z
        vy = (1 - vx * n[0]) / n[1] - 0.5 * w
        return trapezoid(np.hypot(vx, vy + w * s), s)

    best = min(
        (
            minimize(work, z0, method="Nelder-Mead", options={"xatol": 1e-9, "fatol": 1e-12})
            for z0 in ([0.0, 1.0], [-0.5, 2.0], [0.0, 0.0])
        ),
        key=lambda res: res.fun,
    )
    vx, w = best.x
    expected = np.array([vx, (1 - vx * n[0]) / n[1] - 0.5 * w, w])
    np.testing.assert_allclose(table[k], expected, atol=2e-3)
    if psi_deg == 90.0:  # closed form: IRC at x0 = (1 - sqrt 2) / 2
        np.testing.assert_allclose(
            table[k], [0.0, (math.sqrt(2) - 1) / 2 * math.sqrt(2), math.sqrt(2)], atol=1e-6
        )


# ---------------------------------------------------------------------------- collisions, walls


def test_a_pushed_sphere_pushes_the_next_one_and_they_never_overlap():
    gap = 50 * nm
    a, b = Sphere(0, 0.0, 0.0, R_P), Sphere(1, 2 * R_P + gap, 0.0, R_P)
    sample = Sample(spheres=[a, b])
    px, py = line(-400 * nm, 0.0, 800 * nm, 0.0, 12001)
    for chunk in range(0, 12000, 500):  # the same path in pieces, checked between
        result = push_along_path(
            sample, px[chunk : chunk + 501], py[chunk : chunk + 501], DT, ContactParams()
        )
        assert math.hypot(b.x - a.x, b.y - a.y) >= 2 * R_P - 1e-12
    travel = 800 * nm - (-D)
    assert a.x == pytest.approx(travel, abs=1e-12)
    assert b.x == pytest.approx(2 * R_P + gap + travel - gap, abs=1e-12)
    assert b.x - a.x == pytest.approx(2 * R_P, abs=1e-12)
    assert set(result.moved_ids) == {0, 1}


def test_glancing_chain_and_rod_collisions_leave_no_overlaps():
    spheres = [
        Sphere(0, 0.0, 0.0, R_P),
        Sphere(1, 230 * nm, 70 * nm, 80 * nm),
        Sphere(2, 430 * nm, -60 * nm, 90 * nm),
    ]
    rods = [
        Rod(3, 700 * nm, 100 * nm, math.radians(80), 500 * nm, 20 * nm),
        Rod(4, 820 * nm, -150 * nm, math.radians(20), 400 * nm, 15 * nm),
    ]
    sample = Sample(spheres=spheres, rods=rods)
    px, py = line(-400 * nm, 10 * nm, 1500 * nm, -30 * nm, 30001)
    result = push_along_path(sample, px, py, DT, ContactParams())
    assert len(result.moved_ids) >= 3

    def axis(o):
        if isinstance(o, Rod):
            a, b = o.endpoints()
            return np.linspace(a, b, 2001)
        return np.array([[o.x, o.y]])

    objs = sample.movable
    for i, oi in enumerate(objs):
        for oj in objs[i + 1 :]:
            pi, pj = axis(oi), axis(oj)
            dist = np.min(
                np.hypot(pi[:, None, 0] - pj[None, :, 0], pi[:, None, 1] - pj[None, :, 1])
            )
            assert dist >= oi.radius + oj.radius - 0.01 * nm


def test_electrodes_stop_pushed_objects():
    wall = Electrode(9, 400 * nm, -1000 * nm, 2000 * nm, 1000 * nm, 50 * nm)
    sphere = Sphere(0, 0.0, 0.0, R_P)
    rod = Rod(1, 0.0, -600 * nm, math.radians(90), 300 * nm, 20 * nm)
    sample = Sample(spheres=[sphere], rods=[rod], electrodes=[wall])
    before = (wall.x0, wall.x1, wall.y0, wall.y1)
    params = ContactParams()
    push_along_path(sample, *line(-300 * nm, 0.0, 1200 * nm, 0.0, 15001), DT, params)
    push_along_path(sample, *line(-300 * nm, -600 * nm, 1200 * nm, -600 * nm, 15001), DT, params)
    assert (wall.x0, wall.x1, wall.y0, wall.y1) == before
    assert sphere.x == pytest.approx(wall.x0 - R_P, abs=1e-12)  # stopped flush against the wall
    assert sphere.y == pytest.approx(0.0, abs=1e-12)
    ends = np.array(rod.endpoints())
    assert ends[:, 0].max() == pytest.approx(wall.x0 - rod.radius, abs=1e-12)
    assert ends[:, 0].max() > 200 * nm  # it did travel up to the wall


# ---------------------------------------------------------------------------- forces


def test_lateral_force_is_substrate_sliding_then_the_pushed_objects_friction():
    params = ContactParams()
    n = 10001
    px, py = line(-500 * nm, 0.0, 500 * nm, 0.0, n)
    speed = (px[1] - px[0]) / DT
    sample = Sample(spheres=[Sphere(0, 0.0, 0.0, R_P)])
    result = push_along_path(sample, px, py, DT, params)
    sliding = params.mu_tip_substrate * params.normal_force
    pushing = sliding + params.substrate_friction_force + params.viscous_coefficient * speed
    free = px < -D - 10 * nm
    in_contact = px > -D + 10 * nm
    np.testing.assert_allclose(result.lateral_force[free], sliding, rtol=1e-9)
    np.testing.assert_allclose(result.lateral_force[in_contact], pushing, rtol=1e-6)
    assert pushing > sliding
    k = params.tip_height / params.lateral_spring_constant
    np.testing.assert_allclose(result.lateral_torsion, result.lateral_force * k, rtol=1e-12)
    assert np.all(result.lateral_torsion > 0)
    np.testing.assert_allclose(
        result.vertical_deflection, params.normal_force / params.normal_spring_constant
    )


def test_lateral_force_pushing_a_rod_broadside_is_its_length_friction():
    params = ContactParams()
    L, r = 800 * nm, 20 * nm
    px, py = line(0.0, -400 * nm, 0.0, 200 * nm, 6001)
    speed = (py[1] - py[0]) / DT
    result = push_along_path(Sample(rods=[Rod(0, 0.0, 0.0, 0.0, L, r)]), px, py, DT, params)
    expected = (
        params.mu_tip_substrate * params.normal_force
        + (params.rod_friction_per_length + params.rod_viscous_per_length * speed) * L
    )
    np.testing.assert_allclose(
        result.lateral_force[py > -(R_T + r) + 10 * nm], expected, rtol=1e-6
    )


def test_a_tip_at_rest_feels_no_sliding_friction():
    px = np.concatenate([np.linspace(-500 * nm, -400 * nm, 101), np.full(100, -400 * nm)])
    result = push_along_path(Sample(), px, np.zeros_like(px), DT, ContactParams())
    assert np.all(result.lateral_force[1:101] > 0)
    assert np.all(result.lateral_force[101:] == 0)


# ---------------------------------------------------------------------------- speed


def test_a_long_push_through_thirty_particles_is_fast():
    rng = np.random.default_rng(3)
    spheres = []
    while len(spheres) < 30:
        x, y = rng.uniform(0, 5e-6), rng.uniform(-300 * nm, 300 * nm)
        if all(math.hypot(x - s.x, y - s.y) > 2 * R_P + 20 * nm for s in spheres):
            spheres.append(Sphere(len(spheres), x, y, R_P))
    sample = Sample(spheres=spheres)
    px, py = line(-300 * nm, 0.0, 5.3e-6, 0.0, 100_000)
    push_along_path(
        Sample(spheres=[Sphere(0, 0.0, 0.0, R_P)]),
        *line(-300 * nm, 0, 0, 0, 10),
        DT,
        ContactParams(),
    )  # one-time tables out of the timing
    t0 = time.perf_counter()
    result = push_along_path(sample, px, py, DT, ContactParams())
    elapsed = time.perf_counter() - t0
    assert result.lateral_force.shape == (100_000,)
    assert len(result.moved_ids) > 5
    assert elapsed < 2.0


def test_a_path_fed_in_disjoint_pieces_pushes_as_if_fed_at_once():
    """The instrument feeds long moves in chunks; the contact must carry over between them."""
    px, py = line(-400 * nm, 0.0, 600 * nm, 0.0, 10001)
    whole = Sample(spheres=[Sphere(0, 0.0, 0.0, R_P)])
    push_along_path(whole, px, py, DT, ContactParams())
    pieces = Sample(spheres=[Sphere(0, 0.0, 0.0, R_P)])
    for index in np.array_split(np.arange(px.size), 7):
        push_along_path(pieces, px[index], py[index], DT, ContactParams())
    assert pieces.spheres[0].x == pytest.approx(600 * nm + D, abs=1e-12)
    assert pieces.spheres[0].x == pytest.approx(whole.spheres[0].x, abs=1e-12)


def test_a_tip_starting_on_top_of_a_particle_rides_over_it():
    sample = Sample(spheres=[Sphere(0, 0.0, 0.0, R_P)])
    result = push_along_path(
        sample, *line(-20 * nm, 0.0, 400 * nm, 0.0, 2001), DT, ContactParams()
    )
    assert (sample.spheres[0].x, sample.spheres[0].y) == (0.0, 0.0)
    assert result.moved_ids == []

"""Exactness of the integrators that locate events, against closed forms (docs/theory.md §4, §7, §8):
the located impact times of a bouncing ball, a lift-off at its closed-form instant (and at once where
the separating acceleration is small), and the adaptive integrator's global error against rtol.
Public API only (ms.run, ms.SceneBuilder), so that the tests outlive the drivers' internals."""

from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.special import ellipj, ellipk

import moreau_sim as ms

ROOT = Path(__file__).resolve().parents[1]
BALL = ROOT / "scenes" / "bouncing_ball.toml"
G = 9.81  # [m/s^2] the scenes' gravity
LOCATORS = ["event-driven", "adaptive"]


# ---- located impact times --------------------------------------------------------------------

@pytest.mark.parametrize("integrator", LOCATORS)
@pytest.mark.parametrize("e", [0.5, 0.8, 1.0])
def test_located_impact_times_are_the_closed_form_to_1e_12_s(integrator, e):
    """bouncing_ball (centre at 1 m, r = 0.1 m: gap d0 = 0.9 m): t_0 = sqrt(2 d0 / g) and
    t_n = t_0 (1 + 2 e + ... + 2 e^n) (docs/theory.md §4.1). Every impact faster than 1 cm/s is
    located to 1e-12 s (a slower one's instant is fixed only to ulp(z) / |gamma|)."""
    tr = ms.run(BALL, integrator=integrator, restitution=e, duration=3.0)
    assert tr.complete
    t0 = np.sqrt(2.0 * 0.9 / G)
    exact = t0 * (1.0 + 2.0 * np.cumsum(np.r_[0.0, e ** np.arange(1, 200)]))  # t_0, t_1, ...
    n_fast = int(((G * t0 * e ** np.arange(200) >= 1e-2) & (exact < 3.0)).sum())  # speed g t0 e^n
    exact = exact[:n_fast]
    fast = np.abs(tr.log_gamma_minus) >= 1e-2
    assert fast.sum() == n_fast  # one log row per impact: none missed, none added
    t = tr.log_t[fast]
    assert np.abs(t - exact).max() <= 1e-12
    assert np.allclose(tr.log_gamma_plus[fast], -e * tr.log_gamma_minus[fast], rtol=0.0, atol=1e-12)  # Newton


# ---- lift-off ----------------------------------------------------------------------------------

R_SPHERE, R_BALL = 0.5, 0.1  # [m] a static sphere at the origin, the ball (models/ball.urdf, 1 kg) on top
R = R_SPHERE + R_BALL  # [m] the radius of the path of the ball's centre while in contact


def ball_on_sphere(v0: float, duration: float) -> ms.Scene:
    """The ball's centre at (0, R) over the sphere's centre with horizontal velocity v0 [m/s]; a
    point mass in the x-z plane (translation joint along x and z, no rotation), no ground."""
    b = ms.SceneBuilder("ball_on_sphere", restitution=0.5, dt=duration, duration=duration)
    b.add_body("ball", ROOT / "models" / "ball.urdf", root_joint="translation", axes=[[1, 0, 0], [0, 0, 1]],
               position=[0.0, 0.0, R], q0=[0.0, 0.0], u0=[v0, 0.0])
    b.add_sphere("dome", R_SPHERE, position=[0.0, 0.0, 0.0])
    return b.build()


def lift_off(v0: float) -> tuple[float, float]:
    """(theta*, t*): where and when the ball leaves the sphere. In contact, energy gives
    theta'^2 = v0^2/R^2 + 2 g (1 - cos theta)/R and the normal force m (g cos theta - R theta'^2)
    vanishes at cos theta* = (2 + v0^2/(g R))/3; t* = int_0^theta* dtheta/theta'."""
    th = np.arccos((2.0 + v0 * v0 / (G * R)) / 3.0)
    t, _ = quad(lambda x: 1.0 / np.sqrt(v0 * v0 / R ** 2 + 2.0 * G * (1.0 - np.cos(x)) / R), 0.0, th,
                epsabs=1e-14, epsrel=1e-14, limit=200)
    return th, t


@pytest.mark.parametrize("integrator", LOCATORS)
def test_a_small_separating_acceleration_lifts_off_at_once(integrator):
    """With v0^2 = g R (1 + 1e-4) the contact at the top separates at once with a normal
    acceleration of 1e-4 g: the closed-form lift-off instant is t = 0 and the motion the parabola
    x = v0 t, z = R - g t^2/2, integrated exactly by both (no contact closes again). A touching
    contact kept persistent here would pull the ball round the sphere."""
    v0 = np.sqrt(G * R * (1.0 + 1e-4))
    tr = ms.run(ball_on_sphere(v0, 0.2).with_options(dt=1e-3), integrator=integrator)
    assert tr.complete
    x, z = tr.q[:, 0], tr.q[:, 1]  # displacements from (0, R)
    assert np.abs(x - v0 * tr.t).max() <= 1e-12
    assert np.abs(z + 0.5 * G * tr.t ** 2).max() <= 1e-12
    assert (tr.gap[1:] > 0.0).all() and len(tr.log_t) == 0


@pytest.mark.parametrize("integrator", LOCATORS)
def test_lift_off_from_a_sphere_at_its_closed_form_instant(integrator):
    """v0^2 = g R / 2: the ball rides the sphere and leaves it at cos theta* = 5/6, t* by quadrature
    (lift_off). A run ending 1e-9 s before t* is still in contact (gap 0, on the circle, one persistent
    contact at its last sample); one ending 1e-9 s after has left (none). The release is located
    where the multiplier reaches -1e-9 N (docs/theory.md §7), ~1e-11 s after t*."""
    v0 = np.sqrt(0.5 * G * R)
    th, t_star = lift_off(v0)
    assert 0.1 < t_star < 0.5
    before = ms.run(ball_on_sphere(v0, t_star - 1e-9), integrator=integrator)
    after = ms.run(ball_on_sphere(v0, t_star + 1e-9), integrator=integrator)
    assert before.complete and after.complete
    assert before.n_contacts[-1] == 1 and after.n_contacts[-1] == 0
    # the state at the end: on the circle, 1e-9 s before theta*, to the integrators' accuracy
    x, z = before.q[-1, 0], R + before.q[-1, 1]
    rate = np.sqrt(v0 * v0 / R ** 2 + 2.0 * G * (1.0 - np.cos(th)) / R)  # theta' at theta*
    tol_r, tol = (1e-12, 1e-11) if integrator == "event-driven" else (1e-10, 1e-7)  # rtol 1e-12 / 1e-8
    assert abs(np.hypot(x, z) - R) <= tol_r and abs(np.arctan2(x, z) - (th - 1e-9 * rate)) <= tol


# ---- the adaptive integrator's global error ----------------------------------------------------

def pendulum(theta0: float) -> ms.Scene:
    """models/pendulum.xml (a rod and a bob on a hinge about y), no obstacle, released at theta0 [rad]."""
    b = ms.SceneBuilder("pendulum_free", restitution=0.5, dt=1e-3, duration=2.0)
    b.add_body("pendulum", mjcf=ROOT / "models" / "pendulum.xml", root_joint="fixed", position=[0.0, 0.0, 1.0],
               q0=[theta0])
    return b.build()


def pendulum_exact(tr: ms.Trajectory, theta0: float) -> np.ndarray:
    """The closed form of a rigid pendulum released from rest at theta0: sin(theta/2) = k sn(K - w0 t, k),
    k = sin(theta0/2), w0^2 = m g l / I. m g l and I are read off the run's own energies, which are exact
    functions of (q, u): V = -m g l cos(theta) + c at two samples, T = I theta'^2 / 2 at the fastest."""
    q, u = tr.q[:, 0], tr.u[:, 0]
    i = int(np.argmax(np.abs(u)))
    inertia = 2.0 * tr.kinetic_energy[i] / u[i] ** 2
    j = int(np.argmax(np.abs(np.cos(q) - np.cos(q[0]))))
    mgl = (tr.potential_energy[j] - tr.potential_energy[0]) / (np.cos(q[0]) - np.cos(q[j]))
    k = np.sin(theta0 / 2.0)
    sn = ellipj(ellipk(k * k) - np.sqrt(mgl / inertia) * tr.t, k * k)[0]
    return 2.0 * np.arcsin(k * sn)


def test_adaptive_global_error_is_bounded_by_rtol():
    """Over 2 s (two and a half swings from 1.5 rad), for rtol = atol in 1e-4 ... 1e-10, the largest
    error of theta against the elliptic-function closed form is at most C rtol with C = 1 (measured:
    0.66, 0.17, 0.11, 0.03), and it shrinks with rtol."""
    theta0 = 1.5
    errors = []
    for rtol in (1e-4, 1e-6, 1e-8, 1e-10):
        tr = ms.run(pendulum(theta0), integrator="adaptive", rtol=rtol, atol=rtol)
        assert tr.complete and tr.meta["run"]["steps_fixed"] == 0
        err = float(np.abs(tr.q[:, 0] - pendulum_exact(tr, theta0)).max())
        assert err <= 1.0 * rtol, (rtol, err)
        errors.append(err)
    assert all(b < a for a, b in zip(errors, errors[1:]))

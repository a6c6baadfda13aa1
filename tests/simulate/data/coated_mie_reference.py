#!/usr/bin/python3
"""Reference values for tests/simulate/mie_test.cpp's coated spheres: Bohren and Huffman's
closed form for a concentric coated sphere (Absorption and Scattering of Light by Small
Particles, Wiley 1983, sec. 8.1, eqs. 8.1-8.2: a_n, b_n from A_n, B_n with the Riccati-Bessel
functions of the core and shell arguments) evaluated with mpmath's Bessel functions at 60
digits, independently of raymatch's recursion (Yang 2003). Prints Qext, Qsca, Qback, g and
S1, S2 at a few angles in Bohren and Huffman's conventions (m = n + ik).

Usage: tests/simulate/data/coated_mie_reference.py
"""
import mpmath as mp

mp.mp.dps = 60


def psi(n, z):  # z j_n(z)
    return z * mp.sqrt(mp.pi / (2 * z)) * mp.besselj(n + 0.5, z)


def chi(n, z):  # -z y_n(z)
    return -z * mp.sqrt(mp.pi / (2 * z)) * mp.bessely(n + 0.5, z)


def dpsi(n, z):  # psi_n' = psi_{n-1} - n psi_n / z
    return psi(n - 1, z) - n * psi(n, z) / z


def dchi(n, z):
    return chi(n - 1, z) - n * chi(n, z) / z


def coefficients(m1, x, m2, y):
    terms = int(round(y + 4.05 * y ** (1.0 / 3) + 2))
    a, b = [], []
    for n in range(1, terms + 1):
        p1, dp1 = psi(n, m1 * x), dpsi(n, m1 * x)
        p2, dp2 = psi(n, m2 * x), dpsi(n, m2 * x)
        c2, dc2 = chi(n, m2 * x), dchi(n, m2 * x)
        A = (m2 * p2 * dp1 - m1 * dp2 * p1) / (m2 * c2 * dp1 - m1 * dc2 * p1)
        B = (m2 * p1 * dp2 - m1 * p2 * dp1) / (m2 * dc2 * p1 - m1 * dp1 * c2)
        py, dpy = psi(n, y), dpsi(n, y)
        xiy = py - 1j * chi(n, y)
        dxiy = dpy - 1j * dchi(n, y)
        P, dP = psi(n, m2 * y), dpsi(n, m2 * y)
        C, dC = chi(n, m2 * y), dchi(n, m2 * y)
        fa, ga = dP - A * dC, P - A * C
        fb, gb = dP - B * dC, P - B * C
        a.append((py * fa - m2 * dpy * ga) / (xiy * fa - m2 * dxiy * ga))
        b.append((m2 * py * fb - dpy * gb) / (m2 * xiy * fb - dxiy * gb))
    return a, b


def efficiencies(a, b, y):
    qe = qs = g = 0
    back = 0
    N = len(a)
    for k in range(N):
        n = k + 1
        f = 2 * n + 1
        qe += f * mp.re(a[k] + b[k])
        qs += f * (abs(a[k]) ** 2 + abs(b[k]) ** 2)
        back += f * (-1) ** n * (a[k] - b[k])
        g += f / (n * (n + 1.0)) * mp.re(a[k] * mp.conj(b[k]))
        if k + 1 < N:
            g += n * (n + 2.0) / (n + 1) * mp.re(a[k] * mp.conj(a[k + 1]) + b[k] * mp.conj(b[k + 1]))
    qe *= 2 / y ** 2
    qs *= 2 / y ** 2
    return qe, qs, abs(back) ** 2 / y ** 2, 4 / (y ** 2 * qs) * g


def amplitudes(a, b, theta):
    mu = mp.cos(theta)
    pi0, pi1 = mp.mpf(0), mp.mpf(1)
    s1 = s2 = 0
    for k in range(len(a)):
        n = k + 1
        tau = n * mu * pi1 - (n + 1) * pi0
        f = (2 * n + 1.0) / (n * (n + 1))
        s1 += f * (a[k] * pi1 + b[k] * tau)
        s2 += f * (a[k] * tau + b[k] * pi1)
        pi0, pi1 = pi1, ((2 * n + 1.0) * mu * pi1 - (n + 1) * pi0) / n
    return s1, s2


CASES = [  # core index, core x, shell index, outer x (relative to the medium)
    ("air bubble in a water drop in air", 1.0, 20.0, 1.333, 50.0),
    ("the sample's drop with a bubble", 1.0, 100.0, 1.33885, 313.0),
    ("a cell: nucleus in cytoplasm in water", 1.39 / 1.335 + 0.001j, 8.0, 1.37 / 1.335, 30.0),
]

for name, m1, x, m2, y in CASES:
    a, b = coefficients(mp.mpc(m1), x, mp.mpc(m2), y)
    qe, qs, qb, g = efficiencies(a, b, y)
    print(f"// {name}: m_core {m1}, x_core {x}, m_shell {m2}, x {y} ({len(a)} terms)")
    print(f"{{{mp.nstr(qe, 12)}, {mp.nstr(qs, 12)}, {mp.nstr(qb, 12)}, {mp.nstr(g, 12)}}}")
    for deg in (0, 10, 90):
        s1, s2 = amplitudes(a, b, mp.radians(deg))
        print(f"  {deg} deg: S1 ({mp.nstr(mp.re(s1), 12)}, {mp.nstr(mp.im(s1), 12)}) "
              f"S2 ({mp.nstr(mp.re(s2), 12)}, {mp.nstr(mp.im(s2), 12)})")

"""Independent Hertz references (reviewer's own).
Sphere: Johnson, Contact Mechanics eq. 3.45 on the axis; off axis by numerically superposing Boussinesq's
point-load solution over p = p0 sqrt(1 - r^2/a^2). Cylinder (plane strain): Flamant line-load superposition and
McEwen's closed form (cross-checked); sigma_out = nu (sxx + szz)."""
import numpy as np

def sphere_axis(zr, nu):
    """(s_r, s_z)/p0 on the axis at depth z/a = zr (Johnson 3.45)."""
    zr = np.asarray(zr, float)
    sr = -(1 + nu) * (1 - zr * np.arctan(1 / zr)) + 0.5 / (1 + zr ** 2)
    sz = -1 / (1 + zr ** 2)
    return sr, sz

def sphere_axis_max_vm(nu):
    zr = np.linspace(1e-4, 3, 300001)
    sr, sz = sphere_axis(zr, nu)
    vm = np.abs(sr - sz)
    j = np.argmax(vm)
    return float(vm[j]), float(zr[j])          # vm/p0, depth/a

_NT, _NP = 240, 512
_t, _wt = np.polynomial.legendre.leggauss(_NT)
_t = 0.25 * np.pi * (_t + 1); _wt = 0.25 * np.pi * _wt      # t in [0, pi/2]
_phi = np.arange(_NP) * 2 * np.pi / _NP; _wp = 2 * np.pi / _NP

def sphere_field(X, Y, Z, nu, a=1.0, p0=1.0):
    """6 stresses (sxx, syy, szz, syz, sxz, sxy)/p0 at points (X, Y, Z>0 depth), pressure disc radius a at origin.
    Boussinesq: compressive load along +z (into the solid)."""
    T, PH = np.meshgrid(_t, _phi, indexing="ij")
    W = np.outer(_wt, np.full(_NP, _wp))
    rho = a * np.sin(T); sx = rho * np.cos(PH); sy = rho * np.sin(PH)
    dP = (p0 * np.cos(T) * rho * a * np.cos(T) * W).ravel()        # p rho drho dphi
    sx = sx.ravel(); sy = sy.ravel()
    out = np.zeros((len(X), 6))
    for i, (x, y, z) in enumerate(zip(X, Y, Z)):
        dx, dy = x - sx, y - sy
        r2 = dx * dx + dy * dy; r = np.sqrt(r2); R = np.sqrt(r2 + z * z)
        g = 1 / (R * (R + z))                       # (1 - z/R)/r^2
        f = dP / (2 * np.pi)
        s_r = f * ((1 - 2 * nu) * g - 3 * z * r2 / R ** 5)
        s_t = -f * (1 - 2 * nu) * (g - z / R ** 3)
        s_z = -3 * f * z ** 3 / R ** 5
        t_rz = -3 * f * r * z * z / R ** 5
        with np.errstate(invalid="ignore", divide="ignore"):
            c = np.where(r > 0, dx / r, 1.0); s = np.where(r > 0, dy / r, 0.0)
        out[i] = [np.sum(s_r * c * c + s_t * s * s), np.sum(s_r * s * s + s_t * c * c), np.sum(s_z),
                  np.sum(t_rz * s), np.sum(t_rz * c), np.sum((s_r - s_t) * c * s)]
    return out

def vm6(s):
    sxx, syy, szz, syz, sxz, sxy = s.T
    return np.sqrt(0.5 * ((sxx - syy) ** 2 + (syy - szz) ** 2 + (szz - sxx) ** 2) + 3 * (syz ** 2 + sxz ** 2 + sxy ** 2))

# ---- cylinder, plane strain ---------------------------------------------------------------------
def mcewen(x, z, a=1.0, p0=1.0):
    x = np.asarray(x, float); z = np.asarray(z, float)
    A = a * a - x * x + z * z
    S = np.sqrt(A * A + 4 * x * x * z * z)
    m = np.sqrt(0.5 * (S + A)); n = np.sign(x) * np.sqrt(np.maximum(0.5 * (S - A), 0))
    sx = -(p0 / a) * (m * (1 + (z * z + n * n) / (m * m + n * n)) - 2 * z)
    sz = -(p0 / a) * m * (1 - (z * z + n * n) / (m * m + n * n))
    txz = (p0 / a) * n * (m * m - z * z) / (m * m + n * n)
    return sx, sz, txz

def flamant(x, z, a=1.0, p0=1.0, n=4000):
    t, w = np.polynomial.legendre.leggauss(n)
    th = 0.5 * np.pi * t; wt = 0.5 * np.pi * w       # s = a sin th, p ds = p0 a cos^2 th dth
    s = a * np.sin(th); dP = p0 * a * np.cos(th) ** 2 * wt
    dx = x - s; R2 = dx * dx + z * z
    k = -2 * dP / (np.pi * R2 * R2)
    return np.sum(k * dx * dx * z), np.sum(k * z ** 3), np.sum(k * dx * z * z)

def vm_plane_strain(sx, sz, txz, nu):
    sy = nu * (sx + sz)
    return np.sqrt(0.5 * ((sx - sy) ** 2 + (sy - sz) ** 2 + (sz - sx) ** 2) + 3 * txz ** 2)

def cyl_max_vm(nu, a=1.0):
    xs = np.linspace(0, 2, 401); zs = np.linspace(1e-3, 2.5, 1001)
    Xg, Zg = np.meshgrid(xs, zs, indexing="ij")
    vm = vm_plane_strain(*mcewen(Xg, Zg), nu)
    i, j = np.unravel_index(np.argmax(vm), vm.shape)
    return float(vm[i, j]), float(xs[i]), float(zs[j])

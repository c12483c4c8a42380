"""
The C of the one-sample inverse: controller_node's `inverse` mode, for every family.

A copy, statement for statement, of the bounded root search of control/kernels.py (begin /
update / result with the same solver-state array, so the same candidates are tried in the same
order) around ModelInverse.solve / commit (control/inverse.py) and PositionController's inverse
mode (control/controller.py: a non-finite reference holds the previous one, references are
clamped to [y_min, y_max], the advance compensation). The family supplies pnr_step_ (the output
target: the model's next output) and pnr_quasi_static_ (the quasi-static target).

Not here: the stamp gate and gap filling (a real-time loop runs one call per sample) and the
feedback modes (they need the measured deflection).
"""
from __future__ import annotations

from piezo_narx_ros.export.c_code import c_float, c_macro_number

# The names of control/kernels.py's solver-state slots, in its order (SV_SIZE of them).
SLOTS = ('T', 'LO', 'HI', 'UP', 'TOLU', 'TOLY', 'MAXIT', 'NGRID', 'PH', 'IT', 'A', 'FA', 'B',
         'FB', 'SIDE', 'BU', 'BE', 'BF', 'NEV', 'FUP', 'SLOPE')
TARGET_CODES = {'output': 0, 'quasi_static': 1}
LIMIT_CODES = {'reached': 0, 'voltage': 1, 'slew': 2, 'not_invertible': 3, 'no_reference': 4}


def header(targets, default_target: str, advance_qs: float | None) -> str:
    """Return the inverse's part of pnr_model.h."""
    qs = ('#define PNR_ADVANCE_QUASI_STATIC ' + c_macro_number(advance_qs) +
          '   /* samples the output leads its quasi-static value */\n'
          if advance_qs is not None else '')
    return f"""/* ---- The inverse: a position reference (m) in, the voltage (V) out -------------
 * controller_node's `inverse` mode: each sample, the input within the voltage limits and the
 * slew window whose model value equals the reference, then the model advances on it (its own
 * free run on the commands sent is the state: no sensor). Targets: PNR_TARGET_OUTPUT, the
 * model's next output (the exact one-step inverse); PNR_TARGET_QUASI_STATIC (hysteresis_narx),
 * the output it settles to if the input holds (docs/control.md).                           */
#define PNR_HAS_INVERSE 1
#define PNR_TARGET_OUTPUT {TARGET_CODES['output']}
#define PNR_TARGET_QUASI_STATIC {TARGET_CODES['quasi_static']}
#define PNR_HAS_QUASI_STATIC {int('quasi_static' in targets)}
#define PNR_TARGET_DEFAULT {TARGET_CODES[default_target]}
{qs}/* pnr_inverse_step's answer: why the command missed its target, if it did */
#define PNR_REACHED {LIMIT_CODES['reached']}
#define PNR_LIMIT_VOLTAGE {LIMIT_CODES['voltage']}
#define PNR_LIMIT_SLEW {LIMIT_CODES['slew']}
#define PNR_NOT_INVERTIBLE {LIMIT_CODES['not_invertible']}     /* flat or folding model there */
#define PNR_NO_REFERENCE {LIMIT_CODES['no_reference']}       /* no finite reference yet: u held */
#define PNR_MAX_GRID 64
#define PNR_SOLVER_SIZE {len(SLOTS)}

typedef struct {{
    double u_min, u_max;   /* voltage limits, V */
    double slew_rate;      /* largest change of u, V/s (INFINITY: none) */
    double y_min, y_max;   /* accepted references, m (others are clamped) */
    double advance;        /* samples the output leads the target, compensated as
                              r(k) - advance (r(k) - r(k-1)); NAN: the model's own estimate */
    int target;            /* PNR_TARGET_OUTPUT or PNR_TARGET_QUASI_STATIC */
    double tol;            /* output tolerance of the solve, m */
    double reach_tol;      /* a larger miss is reported as unreachable, m */
    int max_iter;          /* regula falsi iterations */
    int n_grid;            /* grid points of the bracket search, 2 .. PNR_MAX_GRID */
}} pnr_inverse_params_t;

typedef struct {{
    pnr_inverse_params_t p;
    pnr_state_t model;     /* the model's free run on the commands sent */
    double u_prev;         /* the last command, V */
    double y_model;        /* the model's output for it, m: a sensorless position estimate */
    double miss;           /* model value - target of the last solve, m */
    int evaluations;       /* model evaluations of the last solve */
    /* private */
    double max_step_, advance_, last_ref_;
    int has_ref_;
    double sv_[PNR_SOLVER_SIZE], cand_[PNR_MAX_GRID], g_[PNR_MAX_GRID];
}} pnr_inverse_t;

/* The defaults of PositionController: +-200 V (controller_node's own default since issue 19 is
 * the trained input range widened by 5 %: set u_min/u_max so), no slew limit, the model's
 * trained output range widened by 5 % of its span (no clamp when the model file has no range),
 * its default target and advance, tol 1e-11 m, reach_tol 1e-9 m, 30 iterations, a 6-point
 * grid. */
void pnr_inverse_default_params(pnr_inverse_params_t *p);
/* Check p and start from rest: 0, or -1 (inv untouched) for a bad or unsupported parameter. */
int pnr_inverse_init(pnr_inverse_t *inv, const pnr_inverse_params_t *p);
/* The actuator is at rest again (controller_node's ~/reset). */
void pnr_inverse_reset(pnr_inverse_t *inv);
/* One sample: r[PNR_N_OUTPUTS] references (m) -> u[PNR_N_INPUTS] commands (V); returns
 * PNR_REACHED or why the target was missed. A non-finite reference holds the previous one. */
int pnr_inverse_step(pnr_inverse_t *inv, const double *r, double *u);
"""


def source(targets, default_target: str, y_range: tuple[float, float] | None) -> str:
    """Return the inverse's part of pnr_model.c (after the family's definitions)."""
    enum = ',\n'.join(f'    SV_{name}' for name in SLOTS)
    y_min, y_max = (('-INFINITY', 'INFINITY') if y_range is None
                    else (c_float(y_range[0]), c_float(y_range[1])))
    qs_value = ("""    if (inv->p.target == PNR_TARGET_QUASI_STATIC) {
        return pnr_quasi_static_(&inv->model, u);
    }
""" if 'quasi_static' in targets else '')
    qs_adv = ('inv->p.target == PNR_TARGET_QUASI_STATIC ? PNR_ADVANCE_QUASI_STATIC : 0.0'
              if 'quasi_static' in targets else '0.0')
    target_ok = ('p->target != PNR_TARGET_OUTPUT && p->target != PNR_TARGET_QUASI_STATIC'
                 if 'quasi_static' in targets else 'p->target != PNR_TARGET_OUTPUT')
    return f"""/* ---- The inverse (control/kernels.py and inverse.py, statement for statement) */
enum {{
{enum}
}};
#define P_PREV 0.0
#define P_LOCAL 1.0
#define P_GRID 2.0
#define P_REFINE 3.0
#define LOCAL_TRIES 3

/* Python's max(a, b) and min(a, b) (the first argument on ties). */
static double py_max(double a, double b)
{{
    return b > a ? b : a;
}}

static double py_min(double a, double b)
{{
    return b < a ? b : a;
}}

static int sv_begin(double *sv, double *cand, double target, double lo, double hi,
                    double u_prev, double tol_u, double tol_y, int max_iter, int n_grid)
{{
    double up = py_min(py_max(u_prev, lo), hi);
    int ng = n_grid < PNR_MAX_GRID ? n_grid : PNR_MAX_GRID;
    sv[SV_T] = target;
    sv[SV_LO] = lo;
    sv[SV_HI] = hi;
    sv[SV_UP] = up;
    sv[SV_TOLU] = tol_u;
    sv[SV_TOLY] = tol_y;
    sv[SV_MAXIT] = max_iter;
    sv[SV_NGRID] = ng > 2 ? ng : 2;
    sv[SV_PH] = P_PREV;
    sv[SV_IT] = 0.0;
    sv[SV_SIDE] = 0.0;
    sv[SV_BU] = up;
    sv[SV_BE] = INFINITY;
    sv[SV_BF] = NAN;
    sv[SV_NEV] = 0.0;
    cand[0] = up;
    return 1;
}}

/* The grid's sign change nearest u_prev: 1 and the bracket (a, fa, b, fb), or 0. */
static int sv_bracket(const double *sv, const double *cand, const double *g, int n, double *ab)
{{
    double t = sv[SV_T], up = sv[SV_UP], fup = sv[SV_FUP];
    double best_d = INFINITY, a = 0.0, fa = 0.0, b = 0.0, fb = 0.0;
    double e0, e1, x0, x1, d;
    int found = 0, j;
    for (j = 0; j < n - 1; ++j) {{
        e0 = g[j] - t;
        e1 = g[j + 1] - t;
        if (!(isfinite(e0) && isfinite(e1)) || e0 * e1 > 0.0) {{
            continue;
        }}
        x0 = cand[j];
        x1 = cand[j + 1];
        d = (x0 <= up && up <= x1) ? 0.0 : py_min(fabs(x0 - up), fabs(x1 - up));
        if (d < best_d) {{
            best_d = d;
            found = 1;
            a = x0;
            fa = e0;
            b = x1;
            fb = e1;
            if (d == 0.0 && isfinite(fup) && x0 < up && up < x1) {{
                if (fa * fup <= 0.0) {{
                    b = up;
                    fb = fup;
                }} else {{
                    a = up;
                    fa = fup;
                }}
            }}
        }}
    }}
    ab[0] = a;
    ab[1] = fa;
    ab[2] = b;
    ab[3] = fb;
    return found;
}}

static int sv_grid(double *sv, double *cand)
{{
    double lo = sv[SV_LO], hi = sv[SV_HI];
    int m = (int)sv[SV_NGRID], j;
    for (j = 0; j < m; ++j) {{
        cand[j] = lo + (hi - lo) * (double)j / (double)(m - 1);
    }}
    cand[m - 1] = hi;
    sv[SV_PH] = P_GRID;
    return m;
}}

static int sv_refine(double *sv, double *cand, double a, double fa, double b, double fb)
{{
    double x, tmp;
    if (a > b) {{
        tmp = a;
        a = b;
        b = tmp;
        tmp = fa;
        fa = fb;
        fb = tmp;
    }}
    sv[SV_A] = a;
    sv[SV_FA] = fa;
    sv[SV_B] = b;
    sv[SV_FB] = fb;
    sv[SV_PH] = P_REFINE;
    x = fb != fa ? (fb * a - fa * b) / (fb - fa) : 0.5 * (a + b);
    if (!(a < x && x < b)) {{
        x = 0.5 * (a + b);
    }}
    cand[0] = x;
    return 1;
}}

static int sv_secant(double *sv, double *cand, double x0, double e0, double slope)
{{
    double x;
    if (!(isfinite(slope) && slope != 0.0)) {{
        return 0;
    }}
    x = py_min(py_max(x0 - e0 / slope, sv[SV_LO]), sv[SV_HI]);
    if (x == x0) {{
        return 0;
    }}
    cand[0] = x;
    return 1;
}}

static int sv_done(double *sv)
{{
    if (sv[SV_PH] == P_REFINE && sv[SV_B] > sv[SV_A]) {{
        sv[SV_SLOPE] = (sv[SV_FB] - sv[SV_FA]) / (sv[SV_B] - sv[SV_A]);
    }}
    return 0;
}}

static int sv_update(double *sv, double *cand, const double *g, int n)
{{
    double t = sv[SV_T], up = sv[SV_UP];
    double e, ae, x, a, fa, ab[4];
    int j, k;
    for (j = 0; j < n; ++j) {{
        e = g[j] - t;
        sv[SV_NEV] += 1.0;
        ae = isfinite(e) ? fabs(e) : INFINITY;
        if (ae < sv[SV_BE] || (ae == sv[SV_BE] && fabs(cand[j] - up) < fabs(sv[SV_BU] - up))) {{
            sv[SV_BU] = cand[j];
            sv[SV_BE] = ae;
            sv[SV_BF] = e;
        }}
    }}
    if (sv[SV_BE] <= sv[SV_TOLY]) {{
        return sv_done(sv);
    }}
    if (sv[SV_PH] == P_PREV) {{
        e = g[0] - t;
        sv[SV_FUP] = e;
        if (!(sv[SV_HI] - sv[SV_LO] > sv[SV_TOLU]) || !isfinite(e)) {{
            return sv[SV_HI] - sv[SV_LO] > sv[SV_TOLU] ? sv_grid(sv, cand) : 0;
        }}
        sv[SV_A] = up;
        sv[SV_FA] = e;
        sv[SV_PH] = P_LOCAL;
        k = sv_secant(sv, cand, up, e, sv[SV_SLOPE]);
        return k ? k : sv_grid(sv, cand);
    }}
    if (sv[SV_PH] == P_LOCAL) {{
        x = cand[0];
        e = g[0] - t;
        a = sv[SV_A];
        fa = sv[SV_FA];
        if (isfinite(e) && e * fa <= 0.0) {{
            return sv_refine(sv, cand, a, fa, x, e);
        }}
        sv[SV_IT] += 1.0;
        if (!isfinite(e) || sv[SV_IT] >= LOCAL_TRIES) {{
            return sv_grid(sv, cand);
        }}
        sv[SV_A] = x;
        sv[SV_FA] = e;
        k = sv_secant(sv, cand, x, e, (e - fa) / (x - a));
        return k ? k : sv_grid(sv, cand);
    }}
    if (sv[SV_PH] == P_GRID) {{
        if (!sv_bracket(sv, cand, g, n, ab) || !(ab[2] - ab[0] > sv[SV_TOLU])) {{
            return 0;
        }}
        sv[SV_IT] = 0.0;
        return sv_refine(sv, cand, ab[0], ab[1], ab[2], ab[3]);
    }}
    /* Refine: Illinois regula falsi. */
    x = cand[0];
    e = g[0] - t;
    if (!isfinite(e)) {{
        return 0;
    }}
    if (e * sv[SV_FB] > 0.0) {{
        sv[SV_B] = x;
        sv[SV_FB] = e;
        if (sv[SV_SIDE] == -1.0) {{
            sv[SV_FA] *= 0.5;
        }}
        sv[SV_SIDE] = -1.0;
    }} else if (e * sv[SV_FA] > 0.0) {{
        sv[SV_A] = x;
        sv[SV_FA] = e;
        if (sv[SV_SIDE] == 1.0) {{
            sv[SV_FB] *= 0.5;
        }}
        sv[SV_SIDE] = 1.0;
    }} else {{
        return sv_done(sv);
    }}
    sv[SV_IT] += 1.0;
    if (sv[SV_IT] >= sv[SV_MAXIT] || !(sv[SV_B] - sv[SV_A] > sv[SV_TOLU])) {{
        return sv_done(sv);
    }}
    return sv_refine(sv, cand, sv[SV_A], sv[SV_FA], sv[SV_B], sv[SV_FB]);
}}

/* The model's value for input u (m) in the target's sense; the state is untouched. */
static double pnr_value_(const pnr_inverse_t *inv, double u)
{{
    pnr_state_t t;
    double y[PNR_N_OUTPUTS];
{qs_value}    t = inv->model;
    pnr_step_(&t, &u, y);
    return y[0];
}}

void pnr_inverse_default_params(pnr_inverse_params_t *p)
{{
    p->u_min = -200.0;
    p->u_max = 200.0;
    p->slew_rate = INFINITY;
    p->y_min = {y_min};
    p->y_max = {y_max};
    p->advance = NAN;
    p->target = PNR_TARGET_DEFAULT;
    p->tol = 1e-11;
    p->reach_tol = 1e-9;
    p->max_iter = 30;
    p->n_grid = 6;
}}

void pnr_inverse_reset(pnr_inverse_t *inv)
{{
    int i;
    pnr_init(&inv->model);
    for (i = 0; i < PNR_SOLVER_SIZE; ++i) {{
        inv->sv_[i] = 0.0;     /* also the remembered slope: a reset run repeats a fresh one */
    }}
    inv->u_prev = 0.0;
    inv->y_model = 0.0;
    inv->miss = 0.0;
    inv->evaluations = 0;
    inv->last_ref_ = 0.0;
    inv->has_ref_ = 0;
}}

int pnr_inverse_init(pnr_inverse_t *inv, const pnr_inverse_params_t *p)
{{
    if (({target_ok}) || !(p->u_min < p->u_max) || !(p->slew_rate > 0.0) ||
            !(p->y_min < p->y_max) || !(p->tol > 0.0) || !(p->reach_tol >= p->tol) ||
            p->max_iter < 1 || p->n_grid < 2 || p->n_grid > PNR_MAX_GRID ||
            !(isnan(p->advance) || isfinite(p->advance)) || isnan(p->u_min) ||
            isnan(p->u_max)) {{
        return -1;
    }}
    inv->p = *p;
    inv->max_step_ = isfinite(p->slew_rate) ? p->slew_rate / PNR_FS_HZ : INFINITY;
    inv->advance_ = isnan(p->advance) ? ({qs_adv}) : p->advance;
    pnr_inverse_reset(inv);
    return 0;
}}

static void pnr_commit_(pnr_inverse_t *inv, double u)
{{
    double y[PNR_N_OUTPUTS];
    pnr_step_(&inv->model, &u, y);
    inv->y_model = y[0];
    inv->u_prev = u;
}}

int pnr_inverse_step(pnr_inverse_t *inv, const double *ref, double *u_out)
{{
    const pnr_inverse_params_t *p = &inv->p;
    double *sv = inv->sv_;
    double r = ref[0], r_prev, target, lo, hi, u, miss;
    int n, j, limit;
    if (!isfinite(r)) {{
        if (!inv->has_ref_) {{           /* nothing valid yet: hold the actuator */
            u_out[0] = inv->u_prev;
            inv->miss = 0.0;
            inv->evaluations = 0;
            pnr_commit_(inv, inv->u_prev);
            return PNR_NO_REFERENCE;
        }}
        r = inv->last_ref_;
    }} else if (!(p->y_min <= r && r <= p->y_max)) {{
        r = py_min(py_max(r, p->y_min), p->y_max);
    }}
    target = r + 0.0;
    r_prev = inv->has_ref_ ? inv->last_ref_ : r;
    target -= inv->advance_ * (r - r_prev);
    inv->last_ref_ = r;
    inv->has_ref_ = 1;
    lo = py_max(p->u_min, inv->u_prev - inv->max_step_);
    hi = py_min(p->u_max, inv->u_prev + inv->max_step_);
    n = sv_begin(sv, inv->cand_, target, lo, hi, inv->u_prev, 1e-9, p->tol, p->max_iter,
                 p->n_grid);
    while (n > 0) {{
        for (j = 0; j < n; ++j) {{
            inv->g_[j] = pnr_value_(inv, inv->cand_[j]);
        }}
        n = sv_update(sv, inv->cand_, inv->g_, n);
    }}
    u = sv[SV_BU];
    miss = sv[SV_BF];
    inv->miss = miss;
    inv->evaluations = (int)sv[SV_NEV];
    limit = PNR_REACHED;
    if (!(fabs(miss) <= p->reach_tol)) {{
        limit = PNR_NOT_INVERTIBLE;
        if (u == lo || u == hi) {{
            limit = (u == lo ? u == p->u_min : u == p->u_max) ? PNR_LIMIT_VOLTAGE
                                                             : PNR_LIMIT_SLEW;
        }}
    }}
    pnr_commit_(inv, u);
    u_out[0] = u;
    return limit;
}}
"""

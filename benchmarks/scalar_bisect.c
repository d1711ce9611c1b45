/* A plain scalar C loop for the Barth sextic: the seed's stackless t-bisection, one ray
 * at a time (Knoll 2009, ch. 6, Sec. 6.4-6.5, Algorithm 7), as a baseline for
 * benchmarks/bench_implicit.py's `scalar` section.
 *
 * Per ray (`trace_one`):
 *   1. The ray o + t dir is clipped to the domain box [lo, hi] (slab test, t >= 0) and
 *      reparameterised over the segment inside it: p + s D, s in [0, 1], with
 *      p = o + t0 dir and D = (t1 - t0) dir (Sec. 6.5.5.1). A ray that misses the box has
 *      no hit.
 *   2. d_max = ceil(log2(|D| / eps)) (Eq. 6.19), clamped to [0, 30]; a piece of depth d
 *      is s in [k 2^-d, (k + 1) 2^-d] with an integer position k (exact: no float
 *      modulus is needed to know whether a piece is a left or a right child).
 *   3. Depth-first walk from the whole segment (k = 0, d = 0: the seed's rejection
 *      test): the box of the piece (the hull of its end points, padded by 4 relative
 *      ulps so that neighbouring pieces overlap, as jaxiso's ray_boxes do) goes through
 *      the interval extension of f. If the enclosure F holds the isovalue 0 (and is
 *      finite) the piece is a hit at d == d_max, else the walk descends to its left half
 *      (2k, d + 1). If F does not hold 0, the walk moves on to the next piece: up while
 *      the piece is a right child (k odd), then to the right sibling (k + 1); climbing
 *      out of the root ends the walk with no hit (the seed's back-recursion loop, with
 *      the parity of k in place of the modulus t % 2 t_incr).
 *   4. The hit is reported at the MIDPOINT of the accepted piece, t = t0 + (k + 1/2)
 *      2^-d (t1 - t0), as jaxiso reports it (the seed's Algorithm 7 returns the piece's
 *      left end t.x; the two differ by half a piece, at most eps / 2 in world space).
 *   Every box test counts as one step; a ray that reaches max_steps reports no hit.
 *
 * Arithmetic: float32 interval arithmetic rounded to nearest, no directed rounding (the
 * seed's choice, Sec. 6.4.1; jaxiso's rounding="fast"). Products are the hull of the four
 * endpoint products (Eq. 6.5); a product of an interval with itself (x*x) is the tight
 * even square ([-1, 2]^2 = [0, 4], Eq. 6.18). Build with -std=c99 (ISO mode: GCC then
 * contracts no a*b+c into FMAs) so every operation rounds once, like the jaxpr jaxiso
 * evaluates.
 *
 * The function is the Barth sextic of jaxiso/implicit/surfaces.py (_barth_sextic),
 * written out by hand in the order of its jaxpr:
 *   x2 = x*x, y2 = y*y, z2 = z*z          (tight squares)
 *   s  = ((x2 + y2) + z2) - 1
 *   a  = (4 * (T2*x2 - y2)) * (T2*y2 - z2)
 *   f  = a * (T2*z2 - x2) - (C*s) * s     ((C*s)*s: a general product, not a square)
 * with TAU = (1 + sqrt 5) / 2, T2 = TAU*TAU and C = 1 + 2 TAU computed in double and
 * rounded once to float32 (as jax rounds the Python constants). Domain [-1.5, 1.5]^3,
 * isovalue 0.
 *
 * Entry points (ctypes):
 *   int trace(int n, const float *origin, const float *dir, float eps, float lo[3],
 *             float hi[3], int max_steps, float *t_out, int *hit_out, int threads)
 *     origin, dir: [n, 3] row-major; t_out [n] (INFINITY where no hit), hit_out [n]
 *     (0 / 1). Returns the number of hits (-1 for bad arguments).
 *   int trace_steps(..., same as trace ..., int *steps_out)  also writes box tests/ray
 *     (steps_out may be NULL).
 *   void enclose(int n, const float *box_lo, const float *box_hi, float *f_lo,
 *                float *f_hi)  the interval extension on n boxes ([n, 3] corners), for
 *     checking it against jaxiso's.
 *   int parallel_backend(void)  1: OpenMP, 2: pthreads.
 * Rays run in parallel over `threads` threads (OpenMP dynamic schedule, chunks of 64
 * rays, when built with -fopenmp; else pthreads pulling chunks of 64 from a counter).
 */

#ifndef _OPENMP
#define _POSIX_C_SOURCE 200809L
#endif

#include <math.h>
#include <stddef.h>

#ifdef _OPENMP
#include <omp.h>
#else
#include <pthread.h>
#endif

#define MAX_DEPTH 30 /* integer positions stay exact */
#define CHUNK 64
#define OVERLAP (4.0f / 16777216.0f) /* 4 ulps, relative */

typedef struct {
    float lo, hi;
} ival;

/* ------------------------------------------------------------------ interval rules */

static ival i_add(ival a, ival b) {
    ival r = {a.lo + b.lo, a.hi + b.hi};
    return r;
}

static ival i_sub(ival a, ival b) {
    ival r = {a.lo - b.hi, a.hi - b.lo};
    return r;
}

static ival i_sub_c(ival a, float c) {
    ival r = {a.lo - c, a.hi - c};
    return r;
}

/* endpoint product with 0 * inf = 0 (the interval convention) */
static float e_mul(float u, float v) {
    return (u == 0.0f || v == 0.0f) ? 0.0f : u * v;
}

static float min2(float a, float b) { return a < b ? a : b; }
static float max2(float a, float b) { return a > b ? a : b; }

/* hull of the four endpoint products (Eq. 6.5) */
static ival i_mul(ival a, ival b) {
    float p0 = e_mul(a.lo, b.lo), p1 = e_mul(a.lo, b.hi);
    float p2 = e_mul(a.hi, b.lo), p3 = e_mul(a.hi, b.hi);
    ival r = {min2(min2(p0, p1), min2(p2, p3)), max2(max2(p0, p1), max2(p2, p3))};
    return r;
}

/* constant times interval: the product with the point interval [c, c] */
static ival i_mul_c(float c, ival a) {
    ival p = {c, c};
    return i_mul(p, a);
}

/* x*x, the even rule: [mig^2, mag^2], 0 below when the interval straddles 0 */
static ival i_sqr(ival a) {
    float al = fabsf(a.lo), ah = fabsf(a.hi);
    float mag = max2(al, ah);
    float mig = (a.lo <= 0.0f && a.hi >= 0.0f) ? 0.0f : min2(al, ah);
    ival r = {mig * mig, mag * mag};
    return r;
}

/* ------------------------------------------------------------------ the function */

static float T2, C6; /* TAU^2 and 1 + 2 TAU as float32 */

static void constants(void) {
    double tau = (1.0 + sqrt(5.0)) / 2.0;
    T2 = (float)(tau * tau);
    C6 = (float)(1.0 + 2.0 * tau);
}

static ival barth_sextic(ival x, ival y, ival z) {
    ival x2 = i_sqr(x), y2 = i_sqr(y), z2 = i_sqr(z);
    ival s = i_sub_c(i_add(i_add(x2, y2), z2), 1.0f);
    ival a = i_mul_c(4.0f, i_sub(i_mul_c(T2, x2), y2));
    ival b = i_mul(a, i_sub(i_mul_c(T2, y2), z2));
    ival c = i_mul(b, i_sub(i_mul_c(T2, z2), x2));
    ival q = i_mul(i_mul_c(C6, s), s);
    return i_sub(c, q);
}

/* ------------------------------------------------------------------ one ray */

/* the box of p + s D over [s0, s1] on one axis, padded by OVERLAP relative */
static ival axis_box(float p, float D, float s0, float s1) {
    float a = p + D * s0, b = p + D * s1;
    float lo = min2(a, b), hi = max2(a, b);
    float pad = OVERLAP * max2(fabsf(lo), fabsf(hi));
    ival r = {lo - pad, hi + pad};
    return r;
}

/* 2^-d exactly (d in 0..MAX_DEPTH) */
static float piece_width(int d) { return ldexpf(1.0f, -d); }

/* slab clip of o + t d to [lo, hi] within [0, inf): 1 and (t0, t1) if it meets the box */
static int clip(const float *o, const float *d, const float *lo, const float *hi,
                float *t0, float *t1) {
    float near = -INFINITY, far = INFINITY;
    for (int i = 0; i < 3; i++) {
        float ne, fa;
        if (d[i] == 0.0f) {
            int in = o[i] >= lo[i] && o[i] <= hi[i];
            ne = in ? -INFINITY : INFINITY;
            fa = in ? INFINITY : -INFINITY;
        } else {
            float ta = (lo[i] - o[i]) / d[i], tb = (hi[i] - o[i]) / d[i];
            ne = min2(ta, tb);
            fa = max2(ta, tb);
        }
        near = max2(near, ne);
        far = min2(far, fa);
    }
    *t0 = max2(near, 0.0f);
    *t1 = far;
    return *t0 <= *t1 && isfinite(*t1 - *t0);
}

static int trace_one(const float *o, const float *dir, float eps, const float *lo,
                     const float *hi, int max_steps, float *t_out, int *steps_out) {
    float t0, t1;
    *t_out = INFINITY;
    *steps_out = 0;
    if (!clip(o, dir, lo, hi, &t0, &t1)) return 0;
    float len = t1 - t0;
    float p[3], D[3];
    for (int i = 0; i < 3; i++) {
        p[i] = o[i] + t0 * dir[i];
        D[i] = dir[i] * len;
    }
    float L = sqrtf(D[0] * D[0] + D[1] * D[1] + D[2] * D[2]);
    float dm = ceilf(log2f(max2(L, 1e-30f) / eps));
    int d_max = dm < 0.0f ? 0 : (dm > MAX_DEPTH ? MAX_DEPTH : (int)dm);
    int k = 0, d = 0, steps = 0;
    while (steps < max_steps) {
        float w = piece_width(d);
        float s0 = (float)k * w, s1 = (float)(k + 1) * w;
        ival F = barth_sextic(axis_box(p[0], D[0], s0, s1), axis_box(p[1], D[1], s0, s1),
                              axis_box(p[2], D[2], s0, s1));
        steps++;
        int possible = F.lo <= 0.0f && 0.0f <= F.hi; /* false for NaN */
        int finite = isfinite(F.hi - F.lo);
        if (possible && finite && d >= d_max) { /* the hit: midpoint of the piece */
            *t_out = t0 + ((float)k + 0.5f) * w * len;
            *steps_out = steps;
            return 1;
        }
        if (possible && d < d_max) { /* recurse: the left half */
            k *= 2;
            d += 1;
            continue;
        }
        /* next piece: up while a right child, then the right sibling */
        while (d > 0 && (k & 1)) {
            k >>= 1;
            d -= 1;
        }
        if (d == 0) break; /* climbed out of the root: no root on the segment */
        k += 1;
    }
    *steps_out = steps;
    return 0;
}

/* ------------------------------------------------------------------ batch, threads */

typedef struct {
    int n;
    const float *origin, *dir;
    float eps;
    const float *lo, *hi;
    int max_steps;
    float *t_out;
    int *hit_out, *steps_out;
} batch;

static int run_range(const batch *b, int i0, int i1) {
    int hits = 0;
    for (int i = i0; i < i1; i++) {
        int steps;
        int h = trace_one(b->origin + 3 * (size_t)i, b->dir + 3 * (size_t)i, b->eps, b->lo,
                          b->hi, b->max_steps, b->t_out + i, &steps);
        b->hit_out[i] = h;
        if (b->steps_out) b->steps_out[i] = steps;
        hits += h;
    }
    return hits;
}

#ifndef _OPENMP
typedef struct {
    const batch *b;
    pthread_mutex_t *lock;
    int *next;
    int hits;
} worker_arg;

static void *worker(void *arg) {
    worker_arg *w = (worker_arg *)arg;
    for (;;) {
        pthread_mutex_lock(w->lock);
        int i0 = *w->next;
        *w->next = i0 + CHUNK;
        pthread_mutex_unlock(w->lock);
        if (i0 >= w->b->n) break;
        int i1 = i0 + CHUNK < w->b->n ? i0 + CHUNK : w->b->n;
        w->hits += run_range(w->b, i0, i1);
    }
    return NULL;
}

#define MAX_THREADS 256
#endif

int trace_steps(int n, const float *origin, const float *dir, float eps, float lo[3],
                float hi[3], int max_steps, float *t_out, int *hit_out, int threads,
                int *steps_out) {
    if (n < 0 || !(eps > 0.0f) || max_steps < 1) return -1;
    if (threads < 1) threads = 1;
    constants();
    batch b = {n, origin, dir, eps, lo, hi, max_steps, t_out, hit_out, steps_out};
    int hits = 0;
#ifdef _OPENMP
#pragma omp parallel for schedule(dynamic, 64) num_threads(threads) reduction(+ : hits)
    for (int i = 0; i < n; i++) hits += run_range(&b, i, i + 1);
#else
    if (threads > MAX_THREADS) threads = MAX_THREADS;
    if (threads == 1) return run_range(&b, 0, n);
    pthread_t tid[MAX_THREADS];
    worker_arg args[MAX_THREADS];
    pthread_mutex_t lock;
    int next = 0, started = 0;
    pthread_mutex_init(&lock, NULL);
    for (int j = 0; j < threads; j++) {
        args[j].b = &b;
        args[j].lock = &lock;
        args[j].next = &next;
        args[j].hits = 0;
        if (pthread_create(&tid[j], NULL, worker, &args[j]) == 0) started++;
        else break;
    }
    if (started == 0) {
        hits = run_range(&b, 0, n);
    } else {
        for (int j = 0; j < started; j++) {
            pthread_join(tid[j], NULL);
            hits += args[j].hits;
        }
    }
    pthread_mutex_destroy(&lock);
#endif
    return hits;
}

int trace(int n, const float *origin, const float *dir, float eps, float lo[3], float hi[3],
          int max_steps, float *t_out, int *hit_out, int threads) {
    return trace_steps(n, origin, dir, eps, lo, hi, max_steps, t_out, hit_out, threads, NULL);
}

void enclose(int n, const float *box_lo, const float *box_hi, float *f_lo, float *f_hi) {
    constants();
    for (int i = 0; i < n; i++) {
        const float *l = box_lo + 3 * (size_t)i, *h = box_hi + 3 * (size_t)i;
        ival x = {l[0], h[0]}, y = {l[1], h[1]}, z = {l[2], h[2]};
        ival F = barth_sextic(x, y, z);
        f_lo[i] = F.lo;
        f_hi[i] = F.hi;
    }
}

int parallel_backend(void) {
#ifdef _OPENMP
    return 1;
#else
    return 2;
#endif
}

/* A plain C/OpenMP forward rasteriser with the renderer's semantics (DESIGN.md "Rendering
 * semantics", the "classic" anti-aliasing mode), the yardstick of `python -m gvae_core.benchmarks
 * kernels`: what this machine does with a straightforward compiled implementation.
 *
 *   project:   per Gaussian (OpenMP): camera-relative position in double, the rest in float;
 *              2D covariance J W Sigma W^T J^T + 0.3 I (Jacobian centre clamped to 1.3x the half
 *              field of view), SH colour (degree <= 3) + 0.5 clamped at 0, the opacity-aware
 *              footprint sqrt(2 ln(255 o)) standard deviations;
 *   bin:       the tiles each footprint ellipse reaches (exact per tile row), Gaussians sorted by
 *              depth (LSD radix sort of the float bits), pairs sorted by tile (a counting sort
 *              over per-thread tile histograms, stable, so each tile's list is front to back);
 *   composite: per tile (OpenMP, dynamic), per pixel front to back: alpha = min(0.99,
 *              o exp(-q/2)), skipped below 1/255, stop before T < 1e-4, tile done when all pixels
 *              are; the pixel loop is written for the compiler's vectoriser (omp simd).
 *
 * Built by the benchmark with: cc -O3 -march=native -ffast-math -fopenmp -shared -fPIC.
 * Not part of the product: the benchmark times it beside the compiled kernels, in one run. */
#include <math.h>
#include <omp.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#define ALPHA_MAX 0.99f
#define ALPHA_MIN (1.0f / 255.0f)
#define T_MIN 1e-4f
#define NEAR 0.01
#define DILATION 0.3f
#define MAX_AXIS 1e8f

static const float C0 = 0.28209479177387814f, C1 = 0.4886025119029199f;
static const float C2[5] = {1.0925484305920792f, -1.0925484305920792f, 0.31539156525252005f,
                            -1.0925484305920792f, 0.5462742152960396f};
static const float C3[7] = {-0.5900435899266435f, 2.890611442640554f, -0.4570457994644658f,
                            0.3731763325901154f, -0.4570457994644658f, 1.445305721320277f,
                            -0.5900435899266435f};

static double now(void) { return omp_get_wtime(); }

static float clampf(float x, float lo, float hi) { return x < lo ? lo : (x > hi ? hi : x); }

/* cam: R (9, row-major world->camera), centre (3), fx, fy, cx, cy, lo_x, hi_x, lo_y, hi_y,
 * q_cam (4, w x y z: the rotation R as a quaternion). Output per Gaussian: table row of 10
 * floats (mx, my, conic a b c, opacity, r g b, depth), footprint (k, sxx, sxy, syy) double,
 * visible flag. */
static void project(int n, const double *means, const float *log_scales, const float *quats,
                    const float *logits, const float *sh, int k_rest, int degree, const double *cam,
                    int width, int height, float *table, double *foot, uint8_t *visible) {
    const double *R = cam, *C = cam + 9;
    const double fx = cam[12], fy = cam[13], cx = cam[14], cy = cam[15];
    const float lo_x = (float)cam[16], hi_x = (float)cam[17], lo_y = (float)cam[18], hi_y = (float)cam[19];
    const float qw = (float)cam[20], qx0 = (float)cam[21], qy0 = (float)cam[22], qz0 = (float)cam[23];
#pragma omp parallel for schedule(static)
    for (int i = 0; i < n; i++) {
        float *row = table + 10 * (size_t)i;
        double rx = means[3 * i] - C[0], ry = means[3 * i + 1] - C[1], rz = means[3 * i + 2] - C[2];
        float x = (float)(R[0] * rx + R[1] * ry + R[2] * rz);
        float y = (float)(R[3] * rx + R[4] * ry + R[5] * rz);
        float z = (float)(R[6] * rx + R[7] * ry + R[8] * rz);
        visible[i] = 0;
        memset(row, 0, 10 * sizeof(float));
        if (!(z > NEAR) || !isfinite(z)) continue;
        float iz = 1.0f / z, u = x * iz, v = y * iz;
        float j00 = (float)fx * iz, j11 = (float)fy * iz;
        float j02 = -(float)fx * clampf(u, lo_x, hi_x) * iz, j12 = -(float)fy * clampf(v, lo_y, hi_y) * iz;
        /* q = q_cam * normalize(q_gaussian) */
        const float *q = quats + 4 * i;
        float nq = sqrtf(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
        float bw = 1, bx = 0, by = 0, bz = 0;
        if (nq > 1e-12f && isfinite(nq)) { bw = q[0] / nq; bx = q[1] / nq; by = q[2] / nq; bz = q[3] / nq; }
        float w = qw * bw - qx0 * bx - qy0 * by - qz0 * bz, qx = qw * bx + qx0 * bw + qy0 * bz - qz0 * by;
        float qy = qw * by - qx0 * bz + qy0 * bw + qz0 * bx, qz = qw * bz + qx0 * by - qy0 * bx + qz0 * bw;
        float s0 = expf(clampf(log_scales[3 * i], -30.f, 20.f));
        float s1 = expf(clampf(log_scales[3 * i + 1], -30.f, 20.f));
        float s2 = expf(clampf(log_scales[3 * i + 2], -30.f, 20.f));
        float o = 1.0f / (1.0f + expf(-clampf(logits[i], -50.f, 50.f)));
        float m00 = (1 - 2 * (qy * qy + qz * qz)) * s0, m01 = 2 * (qx * qy - w * qz) * s1, m02 = 2 * (qx * qz + w * qy) * s2;
        float m10 = 2 * (qx * qy + w * qz) * s0, m11 = (1 - 2 * (qx * qx + qz * qz)) * s1, m12 = 2 * (qy * qz - w * qx) * s2;
        float m20 = 2 * (qx * qz - w * qy) * s0, m21 = 2 * (qy * qz + w * qx) * s1, m22 = (1 - 2 * (qx * qx + qy * qy)) * s2;
        float a0 = clampf(j00 * m00 + j02 * m20, -MAX_AXIS, MAX_AXIS), a1 = clampf(j00 * m01 + j02 * m21, -MAX_AXIS, MAX_AXIS);
        float a2 = clampf(j00 * m02 + j02 * m22, -MAX_AXIS, MAX_AXIS), b0 = clampf(j11 * m10 + j12 * m20, -MAX_AXIS, MAX_AXIS);
        float b1 = clampf(j11 * m11 + j12 * m21, -MAX_AXIS, MAX_AXIS), b2 = clampf(j11 * m12 + j12 * m22, -MAX_AXIS, MAX_AXIS);
        float aa = a0 * a0 + a1 * a1 + a2 * a2, bb = b0 * b0 + b1 * b1 + b2 * b2, sxy = a0 * b0 + a1 * b1 + a2 * b2;
        float c0 = a1 * b2 - a2 * b1, c1 = a2 * b0 - a0 * b2, c2 = a0 * b1 - a1 * b0;
        float d = DILATION, det = c0 * c0 + c1 * c1 + c2 * c2 + d * (aa + bb) + d * d;
        float sxx = aa + d, syy = bb + d, inv = 1.0f / det;
        float mx = (float)fx * u + (float)cx, my = (float)fy * v + (float)cy;
        if (o < ALPHA_MIN) continue;
        double kk = sqrt(fmax(2.0 * log(255.0 * o), 0.0)) * 1.001 + 1e-4;
        double ex = kk * sqrt((double)sxx), ey = kk * sqrt((double)syy);
        if (mx + ex < 0.5 || mx - ex > width - 0.5 || my + ey < 0.5 || my - ey > height - 0.5) continue;
        /* SH colour along the normalised camera-relative direction */
        double nr = sqrt(rx * rx + ry * ry + rz * rz);
        float dx = 0, dy = 0, dz = 0;
        if (nr > 1e-150) { dx = (float)(rx / nr); dy = (float)(ry / nr); dz = (float)(rz / nr); }
        float basis[15];
        float xx = dx * dx, yy = dy * dy, zz = dz * dz;
        basis[0] = -C1 * dy; basis[1] = C1 * dz; basis[2] = -C1 * dx;
        basis[3] = C2[0] * dx * dy; basis[4] = C2[1] * dy * dz; basis[5] = C2[2] * (2 * zz - xx - yy);
        basis[6] = C2[3] * dx * dz; basis[7] = C2[4] * (xx - yy);
        basis[8] = C3[0] * dy * (3 * xx - yy); basis[9] = C3[1] * dx * dy * dz; basis[10] = C3[2] * dy * (4 * zz - xx - yy);
        basis[11] = C3[3] * dz * (2 * zz - 3 * xx - 3 * yy); basis[12] = C3[4] * dx * (4 * zz - xx - yy);
        basis[13] = C3[5] * dz * (xx - yy); basis[14] = C3[6] * dx * (xx - 3 * yy);
        int kb = (degree + 1) * (degree + 1) - 1;
        const float *coef = sh + (size_t)i * 3 * (k_rest + 1);
        for (int c = 0; c < 3; c++) {
            float col = C0 * coef[c] + 0.5f;
            for (int b = 0; b < kb; b++) col += basis[b] * coef[3 + 3 * b + c];
            row[6 + c] = col > 0 ? col : 0;
        }
        row[0] = mx; row[1] = my;
        row[2] = syy * inv; row[3] = -sxy * inv; row[4] = sxx * inv;
        row[5] = o; row[9] = z;
        foot[4 * i] = kk; foot[4 * i + 1] = sxx; foot[4 * i + 2] = sxy; foot[4 * i + 3] = syy;
        visible[i] = 1;
    }
}

/* For Gaussian i: its tile rows ty0..ty1 and, per row, tile columns [tx0, tx1] (exact ellipse). */
static int row_span(const float *row, const double *f, int ts, int width, int height, int ty,
                    int *tx0, int *tx1) {
    double mx = row[0], my = row[1], k = f[0], sxx = f[1], sxy = f[2], syy = f[3];
    double ey = k * sqrt(syy);
    double lo = fmax(ty * ts + (0.5 - my), -ey);
    double hi = fmin(fmin(ty * ts + ts - 1.0, height - 1.0) + (0.5 - my), ey);
    if (hi < lo) return 0;
    double slope = sxy / syy, ratio = fmax(sxx - sxy * slope, 0.0), peak = k * sxy / sqrt(sxx);
    double dr = fmin(fmax(peak, lo), hi), dl = fmin(fmax(-peak, lo), hi);
    double x_hi = mx + slope * dr + sqrt(ratio * fmax(k * k - dr * dr / syy, 0.0)) + 1e-3;
    double x_lo = mx + slope * dl - sqrt(ratio * fmax(k * k - dl * dl / syy, 0.0)) - 1e-3;
    double x0 = fmax(ceil(x_lo - 0.5), 0.0), x1 = fmin(floor(x_hi - 0.5), width - 1.0);
    if (x1 < x0) return 0;
    *tx0 = (int)((x0 + 0.5) / ts); *tx1 = (int)((x1 + 0.5) / ts);  /* (a float division: idiv is slow) */
    return 1;
}

static void row_range(const float *row, const double *f, int ts, int height, int *ty0, int *ty1) {
    double ey = f[0] * sqrt(f[3]);
    double y0 = fmax(ceil(row[1] - ey - 0.5), 0.0), y1 = fmin(floor(row[1] + ey - 0.5), height - 1.0);
    if (y1 < y0) { *ty0 = 0; *ty1 = -1; return; }
    *ty0 = (int)((y0 + 0.5) / ts); *ty1 = (int)((y1 + 0.5) / ts);
}

/* LSD radix sort (11-bit digits) of idx by key (positive floats' bits sort as integers). */
static void radix_sort(uint32_t *key, int32_t *idx, int n) {
    uint32_t *k2 = malloc(sizeof(uint32_t) * (size_t)n);
    int32_t *i2 = malloc(sizeof(int32_t) * (size_t)n);
    for (int shift = 0; shift < 32; shift += 11) {
        int count[2049] = {0};
        for (int i = 0; i < n; i++) count[((key[i] >> shift) & 2047) + 1]++;
        for (int b = 0; b < 2048; b++) count[b + 1] += count[b];
        for (int i = 0; i < n; i++) {
            int dst = count[(key[i] >> shift) & 2047]++;
            k2[dst] = key[i]; i2[dst] = idx[i];
        }
        memcpy(key, k2, sizeof(uint32_t) * (size_t)n);
        memcpy(idx, i2, sizeof(int32_t) * (size_t)n);
    }
    free(k2); free(i2);
}

static void composite(const float *table, const int32_t *ids, const int64_t *offsets, int tiles_x,
                      int tiles_y, int ts, int width, int height, const float *bg, float *image) {
    int ntiles = tiles_x * tiles_y;
#pragma omp parallel
    {
        int P = ts * ts;
        float *px = malloc(sizeof(float) * P), *py = malloc(sizeof(float) * P);
        float *T = malloc(sizeof(float) * P), *live = malloc(sizeof(float) * P);
        float *acc = malloc(sizeof(float) * 4 * P);
        for (int p = 0; p < P; p++) { px[p] = (float)(p % ts) + 0.5f; py[p] = (float)(p / ts) + 0.5f; }
#pragma omp for schedule(dynamic, 4)
        for (int t = 0; t < ntiles; t++) {
            float x0 = (float)((t % tiles_x) * ts), y0 = (float)((t / tiles_x) * ts);
            for (int p = 0; p < P; p++) { T[p] = 1.0f; live[p] = 1.0f; }
            memset(acc, 0, sizeof(float) * 4 * P);
            float *ar = acc, *ag = acc + P, *ab = acc + 2 * P, *aa = acc + 3 * P;
            int n_live = P;
            for (int64_t k = offsets[t]; k < offsets[t + 1] && n_live > 0; k++) {
                const float *g = table + 10 * (size_t)ids[k];
                float mx = g[0] - x0, my = g[1] - y0, ha = -0.5f * g[2], nb = -g[3], hc = -0.5f * g[4];
                float o = g[5], cr = g[6], cg = g[7], cb = g[8];
                int stopped = 0;
#pragma omp simd reduction(+ : stopped)
                for (int p = 0; p < P; p++) {
                    float dx = px[p] - mx, dy = py[p] - my;
                    float e = dx * (ha * dx + nb * dy) + hc * dy * dy;
                    float alpha = fminf(o * expf(fmaxf(e, -88.0f)), ALPHA_MAX);
                    alpha = alpha >= ALPHA_MIN ? alpha : 0.0f;
                    float tr = T[p], after = tr - tr * alpha;
                    float keep = after >= T_MIN ? live[p] : 0.0f;
                    float wgt = keep * alpha * tr;
                    ar[p] += wgt * cr; ag[p] += wgt * cg; ab[p] += wgt * cb; aa[p] += wgt;
                    stopped += live[p] > keep;
                    T[p] = keep > 0.0f ? after : tr;
                    live[p] = keep;
                }
                n_live -= stopped;
            }
            for (int p = 0; p < P; p++) {
                int col = (int)x0 + p % ts, row = (int)y0 + p / ts;
                if (col >= width || row >= height) continue;
                float *out = image + 3 * ((size_t)row * width + col);
                out[0] = ar[p] + (1.0f - aa[p]) * bg[0];
                out[1] = ag[p] + (1.0f - aa[p]) * bg[1];
                out[2] = ab[p] + (1.0f - aa[p]) * bg[2];
            }
        }
        free(px); free(py); free(T); free(live); free(acc);
    }
}

/* The whole forward pass; seconds of each stage into times[0..2] (project, bin, composite);
 * returns the number of tile-Gaussian pairs. */
int64_t render(int n, const double *means, const float *log_scales, const float *quats,
               const float *logits, const float *sh, int k_rest, int degree, const double *cam,
               int width, int height, int ts, const float *bg, int threads, float *image,
               double *times) {
    omp_set_num_threads(threads);
    double t0 = now();
    float *table = malloc(sizeof(float) * 10 * (size_t)n);
    double *foot = malloc(sizeof(double) * 4 * (size_t)n);
    uint8_t *visible = malloc((size_t)n);
    project(n, means, log_scales, quats, logits, sh, k_rest, degree, cam, width, height, table, foot, visible);
    double t1 = now();
    int tiles_x = (width + ts - 1) / ts, tiles_y = (height + ts - 1) / ts, ntiles = tiles_x * tiles_y;
    int nv = 0;
    for (int i = 0; i < n; i++) nv += visible[i];
    uint32_t *key = malloc(sizeof(uint32_t) * (size_t)(nv + 1));
    int32_t *order = malloc(sizeof(int32_t) * (size_t)(nv + 1));
    for (int i = 0, j = 0; i < n; i++)
        if (visible[i]) { float z = table[10 * (size_t)i + 9]; memcpy(&key[j], &z, 4); order[j++] = i; }
    radix_sort(key, order, nv);
    /* pairs by tile, each tile's list front to back: every thread counts the pairs of its share of
     * the depth-sorted Gaussians per tile, then writes them after the shares before it */
    int nth = threads > 0 ? threads : 1;
    int64_t *hist = calloc((size_t)nth * ntiles, sizeof(int64_t));
    int64_t *offsets = calloc((size_t)ntiles + 1, sizeof(int64_t));
    int32_t *ids = NULL;
    int64_t m = 0;
#pragma omp parallel num_threads(nth)
    {
        int tid = omp_get_thread_num(), nt = omp_get_num_threads();
        int lo = (int)((int64_t)nv * tid / nt), hi = (int)((int64_t)nv * (tid + 1) / nt);
        int64_t *h = hist + (size_t)tid * ntiles;
        for (int j = lo; j < hi; j++) {
            int i = order[j], ty0, ty1, tx0, tx1;
            row_range(table + 10 * (size_t)i, foot + 4 * (size_t)i, ts, height, &ty0, &ty1);
            for (int ty = ty0; ty <= ty1; ty++)
                if (row_span(table + 10 * (size_t)i, foot + 4 * (size_t)i, ts, width, height, ty, &tx0, &tx1))
                    for (int tx = tx0; tx <= tx1; tx++) h[ty * tiles_x + tx]++;
        }
#pragma omp barrier
#pragma omp single
        {
            for (int t = 0; t < ntiles; t++) {
                int64_t c = offsets[t];
                for (int k = 0; k < nt; k++) { int64_t n = hist[(size_t)k * ntiles + t]; hist[(size_t)k * ntiles + t] = c; c += n; }
                offsets[t + 1] = c;
            }
            m = offsets[ntiles];
            ids = malloc(sizeof(int32_t) * (size_t)(m + 1));
        }
        for (int j = lo; j < hi; j++) {
            int i = order[j], ty0, ty1, tx0, tx1;
            row_range(table + 10 * (size_t)i, foot + 4 * (size_t)i, ts, height, &ty0, &ty1);
            for (int ty = ty0; ty <= ty1; ty++)
                if (row_span(table + 10 * (size_t)i, foot + 4 * (size_t)i, ts, width, height, ty, &tx0, &tx1))
                    for (int tx = tx0; tx <= tx1; tx++) ids[h[ty * tiles_x + tx]++] = i;
        }
    }
    double t2 = now();
    composite(table, ids, offsets, tiles_x, tiles_y, ts, width, height, bg, image);
    double t3 = now();
    times[0] = t1 - t0; times[1] = t2 - t1; times[2] = t3 - t2;
    free(table); free(foot); free(visible); free(key); free(order); free(offsets); free(hist); free(ids);
    return m;
}

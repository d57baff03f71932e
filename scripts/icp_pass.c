/* One projective point-to-plane ICP pass (association + the 30 sums) in plain C, one thread: the same
 * float64 math, tests and order as kernels/icp.py (`_target_pixel`, then `_correspondence` and the
 * accumulation), for scripts/bench_icp_ceiling.py, which compiles it with -march=x86-64 and
 * -march=native, and with the floating-point freedoms Taichi gives its kernels by default (fast_math:
 * reassociation, no signed zeros), to see what a compiler does with this pass on this CPU.
 *
 * usage: icp_pass DIR H W REPEATS
 * DIR holds sv.bin sn.bin tv.bin tn.bin (float32 H×W×3: source / target vertex and normal maps, both of
 * the same size here) and
 * params.bin (float64: R row-major 9, t 3, fx fy cx cy, d_thr², cos θ, robust scale). The robust weight
 * is chosen when compiling, as the kernels' is: -DROBUST=0 none, 1 Huber, 2 Tukey; -DDEPTH_WEIGHTED=1
 * for the depth-noise weighting. Prints the best milliseconds over REPEATS passes and the 30 sums (the
 * kernel's order) on one line.
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <time.h>

#ifndef ROBUST
#define ROBUST 1
#endif
#ifndef DEPTH_WEIGHTED
#define DEPTH_WEIGHTED 1
#endif

/* Kinect's depth noise model: its constants come from the build (ti_fusion.sensor.c_defines) */
#if !defined(SIGMA_A) || !defined(SIGMA_B) || !defined(SIGMA_Z0) || !defined(SIGMA_1M)
#error "build with the flags of ti_fusion.sensor.c_defines() (-DSIGMA_A=... -DSIGMA_B=... -DSIGMA_Z0=... -DSIGMA_1M=...)"
#endif

static void *read_file(const char *dir, const char *name, size_t bytes) {
    char path[4096];
    snprintf(path, sizeof path, "%s/%s", dir, name);
    FILE *f = fopen(path, "rb");
    void *p = malloc(bytes);
    if (!f || !p || fread(p, 1, bytes, f) != bytes) {
        fprintf(stderr, "icp_pass: cannot read %zu bytes from %s\n", bytes, path);
        exit(2);
    }
    fclose(f);
    return p;
}

static inline double robust_weight(double r, double qz, double scale) {
    double s = 1.0;
    if (DEPTH_WEIGHTED) {
        double dz = qz - SIGMA_Z0;
        s = SIGMA_1M / (SIGMA_A + SIGMA_B * dz * dz);
    }
    double rn = r * s, w = 1.0;
    if (ROBUST == 1 && fabs(rn) > scale) w = scale / fabs(rn);
    if (ROBUST == 2) {
        double u = 1.0 - (rn / scale) * (rn / scale);
        w = fabs(rn) < scale ? u * u : 0.0;
    }
    return w * s * s;
}

static void icp_pass(int H, int W, const float *restrict sv, const float *restrict sn,
                     const float *restrict tv, const float *restrict tn, const double *restrict P,
                     int *restrict target, double *restrict out) {
    /* the pose, intrinsics and sums in locals: nothing the loops write can change them */
    double R[9], t[3], K[4], sums[30] = {0.0};
    for (int i = 0; i < 9; i++) R[i] = P[i];
    for (int i = 0; i < 3; i++) t[i] = P[9 + i];
    for (int i = 0; i < 4; i++) K[i] = P[12 + i];
    double d2 = P[16], cos_thr = P[17], scale = P[18];
    /* first pass: the target pixel of every source pixel (-1 none, -2 source invalid) */
    for (int k = 0; k < H * W; k++) {
        double px = sv[3 * k], py = sv[3 * k + 1], pz = sv[3 * k + 2];
        double nx = sn[3 * k], ny = sn[3 * k + 1], nz = sn[3 * k + 2];
        double x = R[0] * px + R[1] * py + R[2] * pz + t[0];
        double y = R[3] * px + R[4] * py + R[5] * pz + t[1];
        double z = R[6] * px + R[7] * py + R[8] * pz + t[2];
        double inv_z = 1.0 / z; /* as the kernel: one division, then products */
        double uf = K[0] * x * inv_z + K[2] + 0.5, vf = K[1] * y * inv_z + K[3] + 0.5;
        int inside = z > 0 && uf >= 0 && uf < W && vf >= 0 && vf < H;
        int valid = pz > 0 && nx * nx + ny * ny + nz * nz > 0;
        target[k] = !valid ? -2 : inside ? (int)vf * W + (int)uf : -1;
    }
    /* second pass: the remaining tests, the row and the sums */
    for (int k = 0; k < H * W; k++) {
        int tp = target[k];
        if (tp != -2) sums[29] += 1.0;
        if (tp < 0) continue;
        double qx = tv[3 * tp], qy = tv[3 * tp + 1], qz = tv[3 * tp + 2];
        double mx = tn[3 * tp], my = tn[3 * tp + 1], mz = tn[3 * tp + 2];
        if (!(qz > 0 && mx * mx + my * my + mz * mz > 0)) continue;
        double px = sv[3 * k], py = sv[3 * k + 1], pz = sv[3 * k + 2];
        double x = R[0] * px + R[1] * py + R[2] * pz + t[0];
        double y = R[3] * px + R[4] * py + R[5] * pz + t[1];
        double z = R[6] * px + R[7] * py + R[8] * pz + t[2];
        double dx = x - qx, dy = y - qy, dz = z - qz;
        if (!(dx * dx + dy * dy + dz * dz < d2)) continue;
        double nx = sn[3 * k], ny = sn[3 * k + 1], nz = sn[3 * k + 2];
        double rx = R[0] * nx + R[1] * ny + R[2] * nz;
        double ry = R[3] * nx + R[4] * ny + R[5] * nz;
        double rz = R[6] * nx + R[7] * ny + R[8] * nz;
        if (!(rx * mx + ry * my + rz * mz > cos_thr)) continue;
        double A[6] = {y * mz - z * my, z * mx - x * mz, x * my - y * mx, mx, my, mz};
        double r = mx * dx + my * dy + mz * dz;
        double w = robust_weight(r, qz, scale);
        int e = 0;
        for (int i = 0; i < 6; i++)
            for (int j = i; j < 6; j++) sums[e++] += w * A[i] * A[j];
        for (int i = 0; i < 6; i++) sums[21 + i] += w * A[i] * r;
        sums[27] += r * r;
        sums[28] += 1.0;
    }
    for (int e = 0; e < 30; e++) out[e] = sums[e];
}

int main(int argc, char **argv) {
    if (argc != 5) {
        fprintf(stderr, "usage: icp_pass DIR H W REPEATS\n");
        return 2;
    }
    const char *dir = argv[1];
    int H = atoi(argv[2]), W = atoi(argv[3]), repeats = atoi(argv[4]);
    if (H <= 0 || W <= 0 || repeats <= 0) {
        fprintf(stderr, "icp_pass: H, W and REPEATS must be positive integers\n");
        return 2;
    }
    size_t n = (size_t)H * W * 3;
    float *sv = read_file(dir, "sv.bin", n * sizeof(float)), *sn = read_file(dir, "sn.bin", n * sizeof(float));
    float *tv = read_file(dir, "tv.bin", n * sizeof(float)), *tn = read_file(dir, "tn.bin", n * sizeof(float));
    double *P = read_file(dir, "params.bin", 19 * sizeof(double));
    int *target = malloc((size_t)H * W * sizeof *target);
    double sums[30], best = 1e30;
    for (int rep = 0; rep < repeats; rep++) {
        struct timespec a, b;
        clock_gettime(CLOCK_MONOTONIC, &a);
        icp_pass(H, W, sv, sn, tv, tn, P, target, sums);
        clock_gettime(CLOCK_MONOTONIC, &b);
        double ms = (b.tv_sec - a.tv_sec) * 1e3 + (b.tv_nsec - a.tv_nsec) * 1e-6;
        if (ms < best) best = ms;
    }
    printf("%.6f", best);
    for (int e = 0; e < 30; e++) printf(" %.17g", sums[e]);
    printf("\n");
    return 0;
}

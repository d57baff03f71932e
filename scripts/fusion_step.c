/* One fusion step (Keller's association order) in plain C, single-threaded: the ceiling benchmark's
 * reference for what compiled code makes of the step on this machine (scripts/bench_fusion_ceiling.py
 * builds, runs and checks it).
 *
 * The same step as kernels/fusion.py with the default FusionConfig (association "compatible", radial
 * confidence weights from a per-pixel table, covered pixels skipped, unstable surfels removed, no
 * free-space removal): the frame's measurements turned into the world frame; every surfel projected,
 * tested against the measurement at its pixel, and the compatible ones listed; per pixel the nearest
 * listed surfel (exact depth ties to the smaller index); those surfels merged; the valid pixels left,
 * unless a neighbour's merged disc covers them, appended in row-major order; unstable surfels removed,
 * the k-th survivor at or above the new count filling the k-th hole below it. The loops keep the
 * kernels' shapes (a projection pass and a test pass per block of 128 surfels, branch-free), and where a
 * single thread allows it they are simpler: the index map is one pass, as surfels come in index order.
 *
 *   fusion_step DIR REPEATS     reads DIR/ *.bin (written by the script), runs the step REPEATS times on
 *                               a fresh copy of the map, prints the best ms and the counts, and writes
 *                               the map after the last run to DIR/out_*.bin
 */
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#define BLOCK 128
#define INT_MAX_ 2147483647
#define FAR 1e10f
#define COVERED (-2)
#define SQRT2 1.41421356237f
#define MIN_COS_VIEW 0.2f

typedef struct { float *position, *normal, *color, *weight, *radius; int32_t *t_created, *t_updated; } Map;

static void *read_file(const char *dir, const char *name, size_t *bytes) {
  char path[4096];
  snprintf(path, sizeof path, "%s/%s", dir, name);
  FILE *f = fopen(path, "rb");
  if (!f) { fprintf(stderr, "fusion_step: cannot open %s\n", path); exit(2); }
  fseek(f, 0, SEEK_END);
  *bytes = (size_t)ftell(f);
  fseek(f, 0, SEEK_SET);
  void *p = malloc(*bytes ? *bytes : 1);
  if (fread(p, 1, *bytes, f) != *bytes) { fprintf(stderr, "fusion_step: short read %s\n", path); exit(2); }
  fclose(f);
  return p;
}

static void write_file(const char *dir, const char *name, const void *p, size_t bytes) {
  char path[4096];
  snprintf(path, sizeof path, "%s/%s", dir, name);
  FILE *f = fopen(path, "wb");
  if (!f || fwrite(p, 1, bytes, f) != bytes) { fprintf(stderr, "fusion_step: cannot write %s\n", path); exit(2); }
  fclose(f);
}

static inline int32_t float_bits(float z) { int32_t k; memcpy(&k, &z, 4); return k; }

static inline void rigid(const float *T, const float *p, float *out) {  /* R (row-major) p + t */
  out[0] = T[0] * p[0] + T[1] * p[1] + T[2] * p[2] + T[9];
  out[1] = T[3] * p[0] + T[4] * p[1] + T[5] * p[2] + T[10];
  out[2] = T[6] * p[0] + T[7] * p[1] + T[8] * p[2] + T[11];
}

static inline void rotate(const float *T, const float *p, float *out) {
  out[0] = T[0] * p[0] + T[1] * p[1] + T[2] * p[2];
  out[1] = T[3] * p[0] + T[4] * p[1] + T[5] * p[2];
  out[2] = T[6] * p[0] + T[7] * p[1] + T[8] * p[2];
}

static inline float dot3(const float *a, const float *b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }

static inline float measurement_radius(float z, float nz, float f) {
  float c = fabsf(nz);
  return SQRT2 * z / (f * (c > MIN_COS_VIEW ? c : MIN_COS_VIEW));
}

typedef struct {  /* inputs of one step */
  int W, H, frame, unstable_age;
  const float *to_camera, *to_world;  /* 12 floats each: R row-major, then t */
  float fx, fy, cx, cy, dist_threshold, cos_threshold, unstable_weight;
  const float *vertex, *normal, *radial;  /* the frame: H×W×3, H×W×3, H×W */
  const uint8_t *rgb;                     /* H×W×3 */
} Frame;

typedef struct {  /* per-step scratch */
  float *world_vertex, *world_normal, *pc, *nc, *rad;  /* per pixel (pc, nc, rad: the merged surfel) */
  int32_t *depth_key, *index, *assoc;                  /* per pixel */
  int32_t *proj_pixel, *depth_bits;                    /* per surfel of the map before the step */
  int32_t block_list[BLOCK], block_keys[BLOCK];        /* a block's compatible surfels and their depths */
  int32_t *removals, *holes, *movers;                  /* per surfel after the appends */
} Scratch;

typedef struct { int merged, added, covered, removed; } Counts;

/* One step on map m of *n surfels (room for the appends); returns what it did. */
static Counts fusion_step(Map *m, int *n, const Frame *fr, Scratch *s) {
  const int W = fr->W, H = fr->H, P = W * H, n0 = *n;
  Counts c = {0, 0, 0, 0};
  /* the measurements in the world frame (FAR and zero where invalid) */
  for (int p = 0; p < P; p++) {
    const float *q = fr->vertex + 3 * p, *nq = fr->normal + 3 * p;
    int valid = q[2] > 0 && dot3(nq, nq) > 0;
    float qw[3], nw[3];
    rigid(fr->to_world, q, qw);
    rotate(fr->to_world, nq, nw);
    for (int k = 0; k < 3; k++) {
      s->world_vertex[3 * p + k] = valid ? qw[k] : FAR;
      s->world_normal[3 * p + k] = valid ? nw[k] : 0.0f;
    }
    s->depth_key[p] = INT_MAX_;
    s->index[p] = INT_MAX_;
  }
  /* filter passes 1 and 2 per block: project, then test against the measurement at the pixel; then the
     compatible surfels of the block claim their pixels (nearest depth; ties keep the smaller index, which
     came first) */
  const float *Tc = fr->to_camera;
  const float dist2 = fr->dist_threshold * fr->dist_threshold;
  for (int lo = 0; lo < n0; lo += BLOCK) {
    int hi = lo + BLOCK < n0 ? lo + BLOCK : n0;
    for (int i = lo; i < hi; i++) {
      float pcam[3];
      rigid(Tc, m->position + 3 * i, pcam);
      float inv_z = 1.0f / pcam[2];
      float uf = fr->fx * pcam[0] * inv_z + fr->cx + 0.5f, vf = fr->fy * pcam[1] * inv_z + fr->cy + 0.5f;
      int inside = (pcam[2] > 0) & (uf >= 0.0f) & (uf < W) & (vf >= 0.0f) & (vf < H);
      int u = inside ? (int)uf : 0, v = inside ? (int)vf : 0;
      u = u < W - 1 ? u : W - 1;
      v = v < H - 1 ? v : H - 1;
      s->proj_pixel[i] = inside ? v * W + u : -1;
      s->depth_bits[i] = float_bits(fabsf(pcam[2]));
    }
    int found = 0;
    for (int i = lo; i < hi; i++) {
      int pix = s->proj_pixel[i], at = pix > 0 ? pix : 0;
      const float *qw = s->world_vertex + 3 * at, *nw = s->world_normal + 3 * at;
      const float *p = m->position + 3 * i;
      float d[3] = {p[0] - qw[0], p[1] - qw[1], p[2] - qw[2]};
      int ok = (pix >= 0) & (dot3(nw, nw) > 0) & (dot3(d, d) <= dist2) &
               (dot3(m->normal + 3 * i, nw) >= fr->cos_threshold);
      s->block_list[found] = i;  /* written always, kept by the count */
      s->block_keys[found] = s->depth_bits[i];
      found += ok;
    }
    for (int k = 0; k < found; k++) {
      int i = s->block_list[k], key = s->block_keys[k], pix = s->proj_pixel[i];
      if (key < s->depth_key[pix]) {
        s->depth_key[pix] = key;
        s->index[pix] = i;
      }
    }
  }
  /* merge: each claimed surfel averages in its pixel's measurement */
  const float *Tw = fr->to_world;
  for (int p = 0; p < P; p++) {
    int i = s->index[p];
    s->assoc[p] = i == INT_MAX_ ? -1 : i;
  }
  for (int p = 0; p < P; p++) {
    int i = s->assoc[p];
    if (i < 0) continue;
    const float *q = fr->vertex + 3 * p, *nq = fr->normal + 3 * p;
    float a = fr->radial[p], w = m->weight[i], qw[3], nw[3], nsum[3];
    rigid(Tw, q, qw);
    rotate(Tw, nq, nw);
    for (int k = 0; k < 3; k++) {
      m->position[3 * i + k] = (w * m->position[3 * i + k] + a * qw[k]) / (w + a);
      nsum[k] = w * m->normal[3 * i + k] + a * nw[k];
    }
    float len = sqrtf(dot3(nsum, nsum));
    if (len > 0)
      for (int k = 0; k < 3; k++) m->normal[3 * i + k] = nsum[k] / len;
    for (int k = 0; k < 3; k++)
      m->color[3 * i + k] = (w * m->color[3 * i + k] + a * (float)fr->rgb[3 * p + k]) / (w + a);
    m->weight[i] = w + a;
    float r = measurement_radius(q[2], nq[2], fr->fx);
    m->radius[i] = m->radius[i] < r ? m->radius[i] : r;
    m->t_updated[i] = fr->frame;
    memcpy(s->pc + 3 * p, m->position + 3 * i, 12);
    memcpy(s->nc + 3 * p, m->normal + 3 * i, 12);
    s->rad[p] = m->radius[i];
    c.merged++;
  }
  /* add, in row-major pixel order, the valid unassociated pixels no neighbour's merged disc covers */
  int k_new = n0;
  for (int v = 0; v < H; v++) {
    for (int u = 0; u < W; u++) {
      int p = v * W + u;
      if (s->assoc[p] != -1) continue;
      const float *q = fr->vertex + 3 * p, *nq = fr->normal + 3 * p;
      if (!(q[2] > 0 && dot3(nq, nq) > 0)) continue;
      float qw[3], nw[3];
      rigid(Tw, q, qw);
      rotate(Tw, nq, nw);
      int covered = 0;
      for (int dv = -1; dv <= 1; dv++)
        for (int du = -1; du <= 1; du++) {
          int y = v + dv, x = u + du;
          if ((dv == 0 && du == 0) || y < 0 || y >= H || x < 0 || x >= W || covered) continue;
          int j = y * W + x;
          if (s->assoc[j] < 0) continue;
          const float *pc = s->pc + 3 * j, *nc = s->nc + 3 * j;
          float d[3] = {qw[0] - pc[0], qw[1] - pc[1], qw[2] - pc[2]};
          float along = dot3(nc, d), r = s->rad[j];
          if (fabsf(along) <= fr->dist_threshold && dot3(d, d) - along * along <= r * r &&
              dot3(nc, nw) >= fr->cos_threshold)
            covered = 1;
        }
      if (covered) {
        s->assoc[p] = COVERED;
        c.covered++;
        continue;
      }
      int k = k_new++;
      memcpy(m->position + 3 * k, qw, 12);
      memcpy(m->normal + 3 * k, nw, 12);
      for (int e = 0; e < 3; e++) m->color[3 * k + e] = (float)fr->rgb[3 * p + e];
      m->weight[k] = fr->radial[p];
      m->radius[k] = measurement_radius(q[2], nq[2], fr->fx);
      m->t_created[k] = fr->frame;
      m->t_updated[k] = fr->frame;
    }
  }
  c.added = k_new - n0;
  /* remove unstable surfels: the k-th survivor at or above the new count fills the k-th hole below it */
  int n1 = k_new, removed = 0;
  for (int i = 0; i < n1; i++) {
    int rm = (m->weight[i] < fr->unstable_weight) & (fr->frame - m->t_updated[i] >= fr->unstable_age);
    s->removals[removed] = i;
    removed += rm;
  }
  int keep = n1 - removed, holes = 0, movers = 0, r = 0;
  for (int k = 0; k < removed; k++) {
    int i = s->removals[k];
    if (i < keep) s->holes[holes++] = i;
  }
  for (int i = keep; i < n1; i++) {  /* survivors at or above keep: skip the listed removals */
    while (r < removed && s->removals[r] < i) r++;
    if (r < removed && s->removals[r] == i) continue;
    s->movers[movers++] = i;
  }
  for (int k = 0; k < holes; k++) {
    int i = s->movers[k], h = s->holes[k];
    memcpy(m->position + 3 * h, m->position + 3 * i, 12);
    memcpy(m->normal + 3 * h, m->normal + 3 * i, 12);
    memcpy(m->color + 3 * h, m->color + 3 * i, 12);
    m->weight[h] = m->weight[i];
    m->radius[h] = m->radius[i];
    m->t_created[h] = m->t_created[i];
    m->t_updated[h] = m->t_updated[i];
  }
  c.removed = removed;
  *n = keep;
  return c;
}

static double now_ms(void) {
  struct timespec t;
  clock_gettime(CLOCK_MONOTONIC, &t);
  return t.tv_sec * 1e3 + t.tv_nsec * 1e-6;
}

int main(int argc, char **argv) {
  if (argc != 3) { fprintf(stderr, "usage: fusion_step DIR REPEATS\n"); return 2; }
  const char *dir = argv[1];
  int repeats = atoi(argv[2]);
  size_t bytes;
  int32_t *ints = read_file(dir, "ints.bin", &bytes);  /* W, H, n, frame, unstable_age */
  float *par = read_file(dir, "params.bin", &bytes);   /* to_camera 12, to_world 12, fx fy cx cy, thresholds */
  Frame fr = {ints[0], ints[1], ints[3], ints[4], par, par + 12, par[24], par[25], par[26], par[27], par[28], par[29],
              par[30], NULL, NULL, NULL, NULL};
  const int n_in = ints[2], P = fr.W * fr.H, cap = n_in + P;
  fr.vertex = read_file(dir, "vertex.bin", &bytes);
  fr.normal = read_file(dir, "normal_map.bin", &bytes);
  fr.radial = read_file(dir, "radial.bin", &bytes);
  fr.rgb = read_file(dir, "rgb.bin", &bytes);
  const char *names[7] = {"position.bin", "normal.bin", "color.bin", "weight.bin", "radius.bin", "t_created.bin",
                          "t_updated.bin"};
  const int width[7] = {12, 12, 12, 4, 4, 4, 4};
  void *orig[7], *work[7];
  for (int a = 0; a < 7; a++) {
    orig[a] = read_file(dir, names[a], &bytes);
    work[a] = malloc((size_t)cap * width[a]);
  }
  Map m = {work[0], work[1], work[2], work[3], work[4], work[5], work[6]};
  static Scratch s;
  s.world_vertex = malloc(12 * (size_t)P);
  s.world_normal = malloc(12 * (size_t)P);
  s.pc = malloc(12 * (size_t)P);
  s.nc = malloc(12 * (size_t)P);
  s.rad = malloc(4 * (size_t)P);
  s.depth_key = malloc(4 * (size_t)P);
  s.index = malloc(4 * (size_t)P);
  s.assoc = malloc(4 * (size_t)P);
  s.proj_pixel = malloc(4 * (size_t)n_in + 4);
  s.depth_bits = malloc(4 * (size_t)n_in + 4);
  s.removals = malloc(4 * (size_t)cap);
  s.holes = malloc(4 * (size_t)cap);
  s.movers = malloc(4 * (size_t)cap);
  double best = 1e30;
  Counts c = {0, 0, 0, 0};
  int n = n_in;
  for (int rep = 0; rep < repeats; rep++) {
    for (int a = 0; a < 7; a++) memcpy(work[a], orig[a], (size_t)n_in * width[a]);  /* a fresh map, untimed */
    n = n_in;
    double t0 = now_ms();
    c = fusion_step(&m, &n, &fr, &s);
    double ms = now_ms() - t0;
    if (ms < best) best = ms;
  }
  printf("%.4f %d %d %d %d %d\n", best, c.merged, c.added, c.covered, c.removed, n);
  for (int a = 0; a < 7; a++) {
    char out[64];
    snprintf(out, sizeof out, "out_%s", names[a]);
    write_file(dir, out, work[a], (size_t)n * width[a]);
  }
  return 0;
}

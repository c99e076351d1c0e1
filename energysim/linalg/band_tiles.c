/* Band Cholesky factorisation and solve of many small symmetric positive definite systems at once.
 *
 * Storage ("tiles"): four matrices interleaved, `a[t][i][r][lane]` = A_(4t+lane)[i + r, i], the lower
 * band of column i (r = 0 .. w - 1, w = u + 1), shape [tiles, n, w, 4], contiguous. One SIMD vector
 * holds the same entry of the four matrices of a tile, so every operation serves four systems, and a
 * tile's columns lie together, so the u columns a new column reads stay in cache.
 *
 * The factorisation is left-looking (column j is A[:, j] less the dot products of the rows of the
 * columns before it), with SB rows of column j accumulated in registers at a time: each load of
 * L[j, i] serves SB multiply-adds, where the right-looking update loads and stores every entry it
 * touches. LAPACK's ?pbtrf factorises one matrix per call and cannot use the batch.
 *
 * The vector type is GCC's / Clang's vector extension: SSE2, AVX2 or NEON instructions, whichever
 * the compiler is told to target. Loads and stores go through memcpy so no alignment is assumed.
 */
#include <math.h>
#include <string.h>

typedef double lanes __attribute__((vector_size(32)));
enum { LANES = 4, SB = 12 };

static inline lanes load(const double *p) {
  lanes x;
  memcpy(&x, p, sizeof x);
  return x;
}

static inline void store(double *p, lanes x) { memcpy(p, &x, sizeof x); }

/* Factorise every tile in place; ok[4t + lane] is set to 0 where that matrix is not positive
 * definite (a pivot not > 0, NaN included). Such a lane goes on with a unit pivot so that its
 * factor stays finite where it can; the caller discards it. */
void band_cholesky_tiles(double *restrict a, long tiles, long n, long w, unsigned char *restrict ok) {
  const long u = w - 1, column = w * LANES;
  for (long t = 0; t < tiles; ++t) {
    double *tile = a + t * n * column;
    for (long j = 0; j < n; ++j) {
      const long rows = n - j < w ? n - j : w;
      double *cj = tile + j * column;
      lanes inverse_pivot = {1.0, 1.0, 1.0, 1.0};
      for (long s0 = 0; s0 < rows; s0 += SB) {
        const long count = rows - s0 < SB ? rows - s0 : SB;
        lanes sum[SB];
        for (long q = 0; q < SB; ++q) sum[q] = q < count ? load(cj + (s0 + q) * LANES) : (lanes){0, 0, 0, 0};
        const long first = j - u > 0 ? j - u : 0;
        /* columns i from `whole` on reach every row s0 .. s0 + SB - 1 of the band: j - i + s0 + SB - 1 <= u */
        long whole = j - (u - s0 - SB + 1);
        if (whole < first) whole = first;
        for (long i = first; i < whole && i < j; ++i) {
          const double *lji = tile + i * column + (j - i) * LANES;
          const lanes l = load(lji);
          const long reach = w - (j - i);
          for (long q = 0; q < count && s0 + q < reach; ++q) sum[q] -= load(lji + (s0 + q) * LANES) * l;
        }
        if (count == SB) {
          for (long i = whole; i < j; ++i) {
            const double *lji = tile + i * column + (j - i) * LANES;
            const lanes l = load(lji);
            const double *lsi = lji + s0 * LANES;
#pragma GCC unroll 16
            for (long q = 0; q < SB; ++q) sum[q] -= load(lsi + q * LANES) * l;
          }
        } else {
          for (long i = whole; i < j; ++i) {
            const double *lji = tile + i * column + (j - i) * LANES;
            const lanes l = load(lji);
            for (long q = 0; q < count; ++q) sum[q] -= load(lji + (s0 + q) * LANES) * l;
          }
        }
        long q0 = 0;
        if (s0 == 0) {
          double pivot[LANES], inverse[LANES];
          store(pivot, sum[0]);
          for (long lane = 0; lane < LANES; ++lane) {
            if (!(pivot[lane] > 0.0)) {
              ok[t * LANES + lane] = 0;
              pivot[lane] = 1.0;
            }
            pivot[lane] = sqrt(pivot[lane]);
            inverse[lane] = 1.0 / pivot[lane];
          }
          store(cj, load(pivot));
          inverse_pivot = load(inverse);
          q0 = 1;
        }
        for (long q = q0; q < count; ++q) store(cj + (s0 + q) * LANES, sum[q] * inverse_pivot);
      }
    }
  }
}

/* Solve L Lᵀ x = b for every tile, with `l` the factors of band_cholesky_tiles and `x` the right-hand
 * sides [tiles, n, 4] on entry, the solutions on return. */
void band_substitute_tiles(const double *restrict l, double *restrict x, long tiles, long n, long w) {
  const long column = w * LANES;
  for (long t = 0; t < tiles; ++t) {
    const double *tile = l + t * n * column;
    double *v = x + t * n * LANES;
    for (long j = 0; j < n; ++j) { /* forward: L y = b, column by column */
      const double *cj = tile + j * column;
      const lanes y = load(v + j * LANES) / load(cj);
      store(v + j * LANES, y);
      const long rows = n - j < w ? n - j : w;
      for (long r = 1; r < rows; ++r) store(v + (j + r) * LANES, load(v + (j + r) * LANES) - load(cj + r * LANES) * y);
    }
    for (long j = n - 1; j >= 0; --j) { /* backward: Lᵀ x = y, row by row */
      const double *cj = tile + j * column;
      const long rows = n - j < w ? n - j : w;
      lanes sum = load(v + j * LANES);
      for (long r = 1; r < rows; ++r) sum -= load(cj + r * LANES) * load(v + (j + r) * LANES);
      store(v + j * LANES, sum / load(cj));
    }
  }
}

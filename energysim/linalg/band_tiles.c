/* Band Cholesky factorisation and solve of many small symmetric positive definite systems at once.
 *
 * Input: the lower bands of B matrices, entry r of column i of matrix b (A_b[i + r, i], r = 0 .. w - 1,
 * w = u + 1) at a[(i * w + r) * entry_stride + b * batch_stride]; batch-last (batch_stride 1) is the
 * layout the compiled Hessian hands over. Each tile of LANES matrices (four in double precision,
 * eight in single) is gathered into a work buffer `[n, w, LANES]` (a short last tile padded with
 * identities), factorised and solved there while it is in cache. One SIMD vector holds the same
 * entry of the matrices of a tile, so every operation serves LANES systems, and a tile's columns
 * lie together, so the u columns a new column reads stay in cache.
 *
 * The factorisation is left-looking (column j is A[:, j] less the dot products of the rows of the
 * columns before it), with SB rows of column j accumulated in registers at a time: each load of
 * L[j, i] serves SB multiply-adds, where the right-looking update loads and stores every entry it
 * touches. LAPACK's ?pbtrf factorises one matrix per call and cannot use the batch.
 *
 * The vector type is GCC's / Clang's vector extension: SSE2, AVX2 or NEON instructions, whichever
 * the compiler is told to target. Loads and stores go through memcpy so no alignment is assumed.
 *
 * The file is built twice into one library (`energysim.linalg.native`): as it stands, in double
 * precision, four systems a 32-byte vector (`band_solve_tiles`), and with -DREAL=float
 * -DSUFFIX=_single, eight systems a vector in single precision (`band_solve_tiles_single`). Each
 * build reads bands of its own precision.
 */
#include <math.h>
#include <string.h>

#ifndef REAL
#define REAL double
#define SUFFIX
#endif
#define JOIN_(a, b) a##b
#define JOIN(a, b) JOIN_(a, b)

typedef REAL lanes __attribute__((vector_size(32)));
enum { LANES = 32 / sizeof(REAL), SB = 12 };

static inline lanes load(const REAL *p) {
  lanes x;
  memcpy(&x, p, sizeof x);
  return x;
}

static inline void store(REAL *p, lanes x) { memcpy(p, &x, sizeof x); }

/* Factorise one tile `[n, w, LANES]` in place; ok[lane] is set to 0 where that matrix is not positive
 * definite (a pivot not > 0, NaN included). Such a lane goes on with a unit pivot so that its
 * factor stays finite where it can; the caller discards it. */
static void factor_tile(REAL *restrict tile, long n, long w, unsigned char *restrict ok) {
  const long u = w - 1, column = w * LANES;
  for (long j = 0; j < n; ++j) {
    const long rows = n - j < w ? n - j : w;
    REAL *cj = tile + j * column;
    lanes inverse_pivot = (lanes){0} + 1;
    for (long s0 = 0; s0 < rows; s0 += SB) {
      const long count = rows - s0 < SB ? rows - s0 : SB;
      lanes sum[SB];
      for (long q = 0; q < SB; ++q) sum[q] = q < count ? load(cj + (s0 + q) * LANES) : (lanes){0};
      const long first = j - u > 0 ? j - u : 0;
      /* columns i from `whole` on reach every row s0 .. s0 + SB - 1 of the band: j - i + s0 + SB - 1 <= u */
      long whole = j - (u - s0 - SB + 1);
      if (whole < first) whole = first;
      for (long i = first; i < whole && i < j; ++i) {
        const REAL *lji = tile + i * column + (j - i) * LANES;
        const lanes l = load(lji);
        const long reach = w - (j - i);
        for (long q = 0; q < count && s0 + q < reach; ++q) sum[q] -= load(lji + (s0 + q) * LANES) * l;
      }
      if (count == SB) {
        for (long i = whole; i < j; ++i) {
          const REAL *lji = tile + i * column + (j - i) * LANES;
          const lanes l = load(lji);
          const REAL *lsi = lji + s0 * LANES;
#pragma GCC unroll 16
          for (long q = 0; q < SB; ++q) sum[q] -= load(lsi + q * LANES) * l;
        }
      } else {
        for (long i = whole; i < j; ++i) {
          const REAL *lji = tile + i * column + (j - i) * LANES;
          const lanes l = load(lji);
          for (long q = 0; q < count; ++q) sum[q] -= load(lji + (s0 + q) * LANES) * l;
        }
      }
      long q0 = 0;
      if (s0 == 0) {
        REAL pivot[LANES], inverse[LANES];
        store(pivot, sum[0]);
        for (long lane = 0; lane < LANES; ++lane) {
          if (!(pivot[lane] > 0.0)) {
            ok[lane] = 0;
            pivot[lane] = 1.0;
          }
          pivot[lane] = (REAL)sqrt(pivot[lane]);
          inverse[lane] = 1 / pivot[lane];
        }
        store(cj, load(pivot));
        inverse_pivot = load(inverse);
        q0 = 1;
      }
      for (long q = q0; q < count; ++q) store(cj + (s0 + q) * LANES, sum[q] * inverse_pivot);
    }
  }
}

/* Solve L Lᵀ x = b for one tile, with `tile` its factors (factor_tile) and `v` the right-hand sides
 * [n, LANES] on entry, the solutions on return. */
static void substitute_tile(const REAL *restrict tile, REAL *restrict v, long n, long w) {
  const long column = w * LANES;
  for (long j = 0; j < n; ++j) { /* forward: L y = b, column by column */
    const REAL *cj = tile + j * column;
    const lanes y = load(v + j * LANES) / load(cj);
    store(v + j * LANES, y);
    const long rows = n - j < w ? n - j : w;
    for (long r = 1; r < rows; ++r) store(v + (j + r) * LANES, load(v + (j + r) * LANES) - load(cj + r * LANES) * y);
  }
  for (long j = n - 1; j >= 0; --j) { /* backward: Lᵀ x = y, row by row */
    const REAL *cj = tile + j * column;
    const long rows = n - j < w ? n - j : w;
    lanes sum = load(v + j * LANES);
    for (long r = 1; r < rows; ++r) sum -= load(cj + r * LANES) * load(v + (j + r) * LANES);
    store(v + j * LANES, sum / load(cj));
  }
}

/* Solve A_b x_b = b_b for the `batch` matrices in `a` and the right-hand sides `x` [tiles, n, LANES]
 * (tiles = ceil(batch / LANES)), which are overwritten by the solutions; ok[b] is set to 0 where A_b
 * is not positive definite. Entry r of column i of matrix b is a[(i * w + r) * entry_stride + b *
 * batch_stride]: batch-last storage (batch_stride 1) is gathered LANES entries at a time, any other
 * lane by lane. `a` is only read; `work` holds n * w * LANES numbers. A tile gathered just before
 * its factorisation stays in cache for the factorisation and both substitutions: its factors never
 * travel through memory. */
void JOIN(band_solve_tiles, SUFFIX)(const REAL *restrict a, long entry_stride, long batch_stride, long batch,
                                    long n, long w, REAL *restrict x, unsigned char *restrict ok,
                                    REAL *restrict work) {
  const long tiles = (batch + LANES - 1) / LANES, entries = n * w;
  for (long t = 0; t < tiles; ++t) {
    const long first = t * LANES, count = batch - first < LANES ? batch - first : LANES;
    if (count == LANES && batch_stride == 1) {
      for (long e = 0; e < entries; ++e)
        memcpy(work + e * LANES, a + e * entry_stride + first, sizeof(REAL) * LANES);
    } else {
      for (long lane = 0; lane < LANES; ++lane) {
        if (lane < count) {
          const REAL *matrix = a + (first + lane) * batch_stride;
          for (long e = 0; e < entries; ++e) work[e * LANES + lane] = matrix[e * entry_stride];
        } else { /* padding: the identity */
          for (long e = 0; e < entries; ++e) work[e * LANES + lane] = e % w == 0 ? 1 : 0;
        }
      }
    }
    factor_tile(work, n, w, ok + first);
    substitute_tile(work, x + t * n * LANES, n, w);
  }
}

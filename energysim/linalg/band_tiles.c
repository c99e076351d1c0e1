/* Band Cholesky factorisation and solve of many small symmetric positive definite systems at once.
 *
 * Input: the lower bands of B matrices, entry r of column i of matrix b (A_b[i + r, i], r = 0 .. w - 1,
 * w = u + 1) at a[(i * w + r) * entry_stride + b * batch_stride]; batch-last (batch_stride 1) is the
 * layout the compiled Hessian hands over. Each tile of LANES matrices (one SIMD vector of them: four
 * doubles or eight floats in 32 bytes, twice as many in 64) is gathered into a work buffer
 * `[n, w, LANES]` (a short last tile padded with identities), factorised and solved there while it is
 * in cache. One SIMD vector holds the same entry of the matrices of a tile, so every operation serves
 * LANES systems, and a tile's columns lie together, so the u columns a new column reads stay in cache.
 *
 * The factorisation is left-looking (column j is A[:, j] less the dot products of the rows of the
 * columns before it), with SB rows of column j accumulated in registers at a time: each load of
 * L[j, i] serves SB multiply-adds, where the right-looking update loads and stores every entry it
 * touches. With COLUMN_PAIRS (built where the CPU has AVX-512, whose 32 vector registers hold both
 * columns' sums) columns j and j + 1 are accumulated together, so each load of a row's L[R, i] serves two
 * multiply-adds, about half the loads per multiply-add: a wide band's factorisation waits on those
 * loads more than on its arithmetic. The operations on each entry, and their order, are those of the
 * single-column form, so both give the same factors to the last bit. LAPACK's ?pbtrf factorises one
 * matrix per call and cannot use the batch.
 *
 * The vector type is GCC's / Clang's vector extension: SSE2, AVX2, AVX-512 or NEON instructions,
 * whichever the compiler is told to target. Loads and stores go through memcpy so no alignment is
 * assumed.
 *
 * The file is built several times into one library (`energysim.linalg.native`): as it stands, in
 * double precision, four systems a 32-byte vector (`band_solve_tiles`); with -DREAL=float
 * -DSUFFIX=_single, eight systems a vector in single precision (`band_solve_tiles_single`); and
 * where the CPU has AVX-512, all with -DCOLUMN_PAIRS and each again with -DVECTOR_BYTES=64 (suffix
 * `_wide`).
 * Each build reads bands of its own precision.
 */
#include <math.h>
#include <stdint.h>
#include <string.h>

#ifndef REAL
#define REAL double
#endif
#ifndef SUFFIX
#define SUFFIX
#endif
#define JOIN_(a, b) a##b
#define JOIN(a, b) JOIN_(a, b)

#ifndef VECTOR_BYTES
#define VECTOR_BYTES 32
#endif

typedef REAL lanes __attribute__((vector_size(VECTOR_BYTES)));
/* PB: the rows of each of two columns in registers at a time (`factor_pair`, 2 PB accumulators) */
enum { LANES = VECTOR_BYTES / sizeof(REAL), SB = 12, PB = 12 };

static inline lanes load(const REAL *p) {
  lanes x;
  memcpy(&x, p, sizeof x);
  return x;
}

static inline void store(REAL *p, lanes x) { memcpy(p, &x, sizeof x); }

/* Store the pivots sqrt(sum) at `at` and return their inverses. A lane whose sum is not > 0 (NaN
 * included) is marked in ok and goes on with a unit pivot, so that its factor stays finite where it
 * can; the caller discards it. */
static inline lanes pivot(REAL *restrict at, lanes sum, unsigned char *restrict ok) {
  REAL pivots[LANES], inverses[LANES];
  store(pivots, sum);
  for (long lane = 0; lane < LANES; ++lane) {
    if (!(pivots[lane] > 0.0)) {
      ok[lane] = 0;
      pivots[lane] = 1.0;
    }
    pivots[lane] = (REAL)sqrt(pivots[lane]);
    inverses[lane] = 1 / pivots[lane];
  }
  store(at, load(pivots));
  return load(inverses);
}

#ifdef COLUMN_PAIRS
/* Columns j and j + 1 (j + 1 < n) of `factor_tile` at once, PB rows at a time. Rows are counted from
 * j (R = j + s): column j holds s = 0 .. u, column j + 1 s = 1 .. u + 1. Both subtract the products
 * with the columns i < j, sharing each load of L[R, i]; column j + 1's own term i = j is subtracted
 * once column j is final, as the single-column form subtracts it last too. */
static void factor_pair(REAL *restrict tile, long n, long w, long j, unsigned char *restrict ok) {
  const long u = w - 1, column = w * LANES;
  REAL *c0 = tile + j * column, *c1 = c0 + column;
  const long rows = n - j < w + 1 ? n - j : w + 1;
  const long first = j - u > 0 ? j - u : 0;
  lanes inverse0 = (lanes){0} + 1, inverse1 = (lanes){0} + 1, coupling = (lanes){0}; /* L[j + 1, j] */
  for (long s0 = 0; s0 < rows; s0 += PB) {
    const long count = rows - s0 < PB ? rows - s0 : PB;
    lanes sum0[PB], sum1[PB];
    for (long q = 0; q < PB; ++q) {
      const long s = s0 + q;
      sum0[q] = q < count && s <= u ? load(c0 + s * LANES) : (lanes){0};
      sum1[q] = q < count && s >= 1 ? load(c1 + (s - 1) * LANES) : (lanes){0};
    }
    /* columns i from `whole` on reach every row of the block (d + s0 + PB - 1 <= u, d = j - i) */
    long whole = j - (u - s0 - PB + 1);
    if (whole < first) whole = first;
    for (long i = first; i < whole && i < j; ++i) {
      const long d = j - i;
      const REAL *li = tile + i * column;
      const lanes l0 = load(li + d * LANES);
      const lanes l1 = d < u ? load(li + (d + 1) * LANES) : (lanes){0}; /* L[j + 1, i], 0 off the band */
      for (long q = 0; q < count && d + s0 + q <= u; ++q) {
        const lanes x = load(li + (d + s0 + q) * LANES);
        sum0[q] -= x * l0;
        sum1[q] -= x * l1;
      }
    }
    for (long i = whole; i < j; ++i) {
      const long d = j - i;
      const REAL *li = tile + i * column;
      const lanes l0 = load(li + d * LANES), l1 = load(li + (d + 1) * LANES);
      const REAL *rows_i = li + (d + s0) * LANES;
      if (count == PB) {
#pragma GCC unroll 16
        for (long q = 0; q < PB; ++q) {
          const lanes x = load(rows_i + q * LANES);
          sum0[q] -= x * l0;
          sum1[q] -= x * l1;
        }
      } else {
        for (long q = 0; q < count; ++q) {
          const lanes x = load(rows_i + q * LANES);
          sum0[q] -= x * l0;
          sum1[q] -= x * l1;
        }
      }
    }
    long q0 = 0;
    if (s0 == 0) {
      inverse0 = pivot(c0, sum0[0], ok);
      q0 = 1;
    }
    for (long q = q0; q < count && s0 + q <= u; ++q) {
      sum0[q] *= inverse0;
      store(c0 + (s0 + q) * LANES, sum0[q]);
    }
    if (s0 == 0) coupling = sum0[1];
    for (long q = 0; q < count; ++q) {
      const long s = s0 + q;
      if (s >= 1 && s <= u) sum1[q] -= sum0[q] * coupling;
    }
    long q1 = 0;
    if (s0 == 0) {
      inverse1 = pivot(c1, sum1[1], ok);
      q1 = 2;
    }
    for (long q = q1; q < count; ++q) store(c1 + (s0 + q - 1) * LANES, sum1[q] * inverse1);
  }
}
#endif

/* Factorise one tile `[n, w, LANES]` in place; ok[lane] is set to 0 where that matrix is not positive
 * definite (a pivot not > 0, NaN included; see `pivot`). */
static void factor_tile(REAL *restrict tile, long n, long w, unsigned char *restrict ok) {
  const long u = w - 1, column = w * LANES;
  long j = 0;
#ifdef COLUMN_PAIRS
  for (; j + 1 < n; j += 2) factor_pair(tile, n, w, j, ok);
#endif
  for (; j < n; ++j) {
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
        inverse_pivot = pivot(cj, sum[0], ok);
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

/* Solve A_b x_b = b_b for the `batch` matrices in `a`. Entry r of column i of matrix b is
 * a[(i * w + r) * entry_stride + b * batch_stride]: batch-last storage (batch_stride 1) is gathered
 * LANES entries at a time, any other lane by lane. b_b is row b of `rhs` `[batch, n]` in the matrices'
 * ordering `order` (entry i of the band systems is DOF order[i] of a row); x_b is written in the
 * same place of `solution` `[batch, n]`, both in double precision whatever REAL is, and zero where
 * A_b is not positive definite (ok[b] set to 0, as LAPACK's path leaves such a row). `a` is only
 * read; `work` holds n * (w + 1) * LANES numbers. A tile gathered just before its factorisation
 * stays in cache for the factorisation and both substitutions: its factors never travel through
 * memory. */
void JOIN(band_solve_tiles, SUFFIX)(const REAL *restrict a, long entry_stride, long batch_stride, long batch,
                                    long n, long w, const double *restrict rhs, const int64_t *restrict order,
                                    double *restrict solution, unsigned char *restrict ok,
                                    REAL *restrict work) {
  const long tiles = (batch + LANES - 1) / LANES, entries = n * w;
  REAL *values = work + entries * LANES;
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
    for (long lane = 0; lane < LANES; ++lane) {
      if (lane < count) {
        const double *row = rhs + (first + lane) * n;
        for (long i = 0; i < n; ++i) values[i * LANES + lane] = (REAL)row[order[i]];
        ok[first + lane] = 1;
      } else {
        for (long i = 0; i < n; ++i) values[i * LANES + lane] = 0;
      }
    }
    factor_tile(work, n, w, ok + first);
    substitute_tile(work, values, n, w);
    for (long lane = 0; lane < count; ++lane) {
      double *row = solution + (first + lane) * n;
      const int solved = ok[first + lane];
      for (long i = 0; i < n; ++i) row[order[i]] = solved ? (double)values[i * LANES + lane] : 0.0;
    }
  }
}

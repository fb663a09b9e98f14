//! Void filling on a window of a raster: a harmonic ("Laplace") fill of a
//! field over its void cells.
//!
//! The field is the difference fine − coarse ("delta surface fill") when a
//! coarser source lies under the raster, or the fine values themselves when
//! none does (the coarse value is then 0). Each void cell takes the value
//! that makes it the mean of its 4 neighbours, with the valid cells around
//! the void held fixed (Dirichlet boundary) and the window's edge acting as a
//! mirror (Neumann). A harmonic function obeys the maximum principle, so the
//! filled field lies within [min, max] of the void's boundary values: with
//! the coarse surface added back, a filled void follows the surrounding
//! terrain and can hold neither a pit nor a wall, while the coarse source
//! still shapes the interior of large voids.
//!
//! Solver: a push-pull pyramid (mean of valid children going up, the parent
//! value coming down) gives a smooth first guess in O(n); successive
//! over-relaxation on the void cells then converges to the harmonic fill.

/// Fill the NaN cells of `grid` (`w` × `h`, row-major) in place. The cells
/// listed in `voids` (all NaN) take the harmonic interpolation of the finite
/// cells 4-adjacent to them; other NaN cells (ones that do not border a void
/// and are not needed) only get the push-pull guess. A window without any
/// finite cell is filled with 0.
pub fn harmonic_fill(grid: &mut [f64], w: usize, h: usize, voids: &[usize]) {
    assert_eq!(grid.len(), w * h);
    if voids.is_empty() {
        return;
    }
    let init = push_pull(grid, w, h);
    grid.copy_from_slice(&init);
    // Successive over-relaxation on the void cells only, then plain
    // Gauss-Seidel sweeps (exact for an isolated void cell).
    relax(grid, w, h, voids, 1.85, 20_000, 1e-4);
    relax(grid, w, h, voids, 1.0, 200, 1e-6);
}

fn relax(
    grid: &mut [f64],
    w: usize,
    h: usize,
    voids: &[usize],
    omega: f64,
    max_iter: usize,
    tol: f64,
) {
    for _ in 0..max_iter {
        let mut worst = 0f64;
        for &i in voids {
            let (x, y) = (i % w, i / w);
            let (mut sum, mut n) = (0f64, 0u32);
            if x > 0 {
                sum += grid[i - 1];
                n += 1;
            }
            if x + 1 < w {
                sum += grid[i + 1];
                n += 1;
            }
            if y > 0 {
                sum += grid[i - w];
                n += 1;
            }
            if y + 1 < h {
                sum += grid[i + w];
                n += 1;
            }
            if n == 0 {
                continue;
            }
            let target = sum / n as f64;
            let step = omega * (target - grid[i]);
            grid[i] += step;
            worst = worst.max(step.abs());
        }
        if worst < tol {
            break;
        }
    }
}

/// Push-pull first guess: every cell of the result holds the grid's value
/// where finite, else an average of the finite cells nearby (0 if none).
fn push_pull(grid: &[f64], w: usize, h: usize) -> Vec<f64> {
    let mut levels: Vec<(Vec<f64>, usize, usize)> = vec![(grid.to_vec(), w, h)];
    loop {
        let (g, lw, lh) = levels.last().unwrap();
        let (lw, lh) = (*lw, *lh);
        if (lw <= 1 && lh <= 1) || !g.iter().any(|v| v.is_nan()) {
            break;
        }
        let (pw, ph) = (lw.div_ceil(2), lh.div_ceil(2));
        let mut p = vec![f64::NAN; pw * ph];
        for py in 0..ph {
            for px in 0..pw {
                let (mut s, mut n) = (0f64, 0u32);
                for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                    let (x, y) = (2 * px + dx, 2 * py + dy);
                    if x < lw && y < lh {
                        let v = g[y * lw + x];
                        if !v.is_nan() {
                            s += v;
                            n += 1;
                        }
                    }
                }
                if n > 0 {
                    p[py * pw + px] = s / n as f64;
                }
            }
        }
        levels.push((p, pw, ph));
    }
    // Pull: fill each level's holes from the (already complete) parent.
    if let Some(top) = levels.last_mut() {
        for v in top.0.iter_mut() {
            if v.is_nan() {
                *v = 0.0;
            }
        }
    }
    for k in (0..levels.len() - 1).rev() {
        let (upper, lower) = levels.split_at_mut(k + 1);
        let (g, lw, lh) = &mut upper[k];
        let (p, pw, _) = &lower[0];
        for y in 0..*lh {
            for x in 0..*lw {
                let v = &mut g[y * *lw + x];
                if v.is_nan() {
                    *v = p[(y / 2) * *pw + x / 2];
                }
            }
        }
    }
    levels.swap_remove(0).0
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plane_is_reproduced_and_bounded() {
        let (w, h) = (30, 20);
        let f = |x: usize, y: usize| 3.0 * x as f64 - 2.0 * y as f64 + 100.0;
        let mut g: Vec<f64> = (0..w * h).map(|i| f(i % w, i / w)).collect();
        for y in 5..15 {
            for x in 8..20 {
                g[y * w + x] = f64::NAN;
            }
        }
        let v: Vec<usize> = (0..g.len()).filter(|&i| g[i].is_nan()).collect();
        harmonic_fill(&mut g, w, h, &v);
        for y in 5..15 {
            for x in 8..20 {
                assert!((g[y * w + x] - f(x, y)).abs() < 0.05, "{x},{y}");
            }
        }
    }

    #[test]
    fn all_void_is_zero_and_single_void_is_neighbour_mean() {
        let mut g = vec![f64::NAN; 6];
        harmonic_fill(&mut g, 3, 2, &[0, 1, 2, 3, 4, 5]);
        assert!(g.iter().all(|&v| v == 0.0));
        let mut g = vec![1.0, 2.0, 3.0, 4.0, f64::NAN, 6.0, 7.0, 8.0, 9.0];
        harmonic_fill(&mut g, 3, 3, &[4]);
        assert!((g[4] - 5.0).abs() < 1e-4);
    }
}

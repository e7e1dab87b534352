//! Where a relit frame's compositing time goes: per covered pixel the candidates evaluated and
//! the hits blended, the surfels' screen radii, and the median time of projection, binning and
//! a whole frame (colour only, back faces culled, as `bench relight` renders).
//!
//! Usage: `cargo run --release --example probe_raster_stats -- RUN [SIZE]` (SIZE² pixels,
//! default 400; the run's first test view).
use radiogs::raster;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let Some(run) = args.get(1).map(std::path::PathBuf::from) else {
        anyhow::bail!("usage: probe_raster_stats RUN [SIZE]");
    };
    let size: u32 = match args.get(2) {
        Some(s) => s.parse().map_err(|e| anyhow::anyhow!("SIZE {s}: {e}"))?,
        None => 400,
    };
    let cfg = radiogs::eval::load_run_config(&run)?;
    let surfels = radiogs::eval::load_run_surfels(&run)?;
    let dataset = radiogs::io::dataset::Dataset::open_downscaled(&cfg.data, cfg.resolution)?;
    let Some(view) = dataset.test.first().or(dataset.train.first()) else {
        anyhow::bail!("{}: no views", cfg.data.display());
    };
    let cam = view.camera.scaled(size, size);
    let settings = radiogs::bench::relight::relit_frame_settings(&cfg);
    let (out, state) = raster::render(&surfels, &cam, &settings, None);
    let weights = raster::blend_weights::BlendWeights::compute(&surfels, &cam, &settings);
    let covered = out.alpha.iter().filter(|&&a| a > 0.01).count().max(1) as f64;
    let pixels = (size * size) as f64;
    let drawn = state.visible.iter().filter(|&&v| v).count();
    println!(
        "{size}²: {} surfels, {drawn} drawn, {} (tile, surfel) pairs, {covered} of {pixels} pixels covered",
        surfels.len(),
        state.tiles.ids.len()
    );
    println!(
        "candidates evaluated: {:.1} per pixel, {:.1} per covered pixel (tile lists: {:.1})",
        state.evaluations_performed as f64 / pixels,
        state.evaluations_performed as f64 / covered,
        state.evaluations as f64 / covered
    );
    println!("hits blended: {:.2} per covered pixel", weights.ids.len() as f64 / covered);
    // Where along each pixel's transmittance the blended hits sit.
    let thresholds = [0.5f32, 0.1, 0.01, 1.0 / 255.0, 1e-3];
    let mut below = [0u64; 5];
    for px in 0..weights.alpha.len() {
        let mut t = 1.0f32;
        for k in weights.offsets[px] as usize..weights.offsets[px + 1] as usize {
            for (b, th) in below.iter_mut().zip(thresholds) {
                *b += (t < th) as u64;
            }
            t -= weights.weights[k];
        }
    }
    println!(
        "hits blended per covered pixel with T below 0.5 / 0.1 / 0.01 / 1/255 / 1e-3: {}",
        below.map(|b| format!("{:.2}", b as f64 / covered)).join(" / ")
    );
    let mut radii: Vec<f32> = state.radii.iter().copied().filter(|&r| r > 0.0).collect();
    radii.sort_by(|a, b| a.total_cmp(b));
    if !radii.is_empty() {
        let q = |f: f64| radii[((radii.len() - 1) as f64 * f) as usize];
        println!("screen radius (px): median {:.2}, 90 % {:.2}, 99 % {:.2}", q(0.5), q(0.9), q(0.99));
    }
    let median_ms = |f: &dyn Fn()| {
        let mut v: Vec<f64> = (0..15)
            .map(|_| {
                let t = std::time::Instant::now();
                f();
                t.elapsed().as_secs_f64() * 1e3
            })
            .collect();
        v.sort_by(|a, b| a.total_cmp(b));
        v[v.len() / 2]
    };
    let projected = raster::project::project(&surfels, &cam, &settings);
    quarter_culling(&projected, &state.tiles, size, settings.filter_inv_square);
    let project_ms = median_ms(&|| {
        raster::project::project(&surfels, &cam, &settings);
    });
    let bin_ms = median_ms(&|| {
        raster::tiles::bin(&projected, size, size, settings.alpha_min, settings.filter_inv_square);
    });
    let frame_ms = median_ms(&|| {
        raster::render(&surfels, &cam, &settings, None);
    });
    println!("median of 15: project {project_ms:.2} ms, bin {bin_ms:.2} ms, whole frame {frame_ms:.2} ms");
    Ok(())
}

/// How many (tile quarter, candidate) pairs the pixel box keeps, how many of those the bin's
/// footprint mask (`TileBins::quarter_masks`) also keeps (the compositor lists a candidate where
/// both do), against the pairs whose α ≥ α_min region reaches a pixel centre of the quarter
/// (ρ ≤ the cut-off, brute force per pixel): the room a tighter per-quarter test would have.
fn quarter_culling(p: &raster::project::Projected, bins: &raster::tiles::TileBins, size: u32, filter_inv_square: f32) {
    const TILE: u32 = 16;
    const QUARTER: u32 = 8;
    let (mut boxed, mut masked, mut reached, mut pixels_reached) = (0u64, 0u64, 0u64, 0u64);
    for ty in 0..bins.tiles_y {
        for tx in 0..bins.tiles_x {
            let t = (ty * bins.tiles_x + tx) as usize;
            let range = bins.offsets[t] as usize..bins.offsets[t + 1] as usize;
            for (&i, &mask) in bins.ids[range.clone()].iter().zip(&bins.quarter_masks[range]) {
                let i = i as usize;
                let b = p.pixels[i];
                for (q, (qx, qy)) in [(0, 0), (1, 0), (0, 1), (1, 1)].into_iter().enumerate() {
                    let (x0, y0) = (tx * TILE + qx * QUARTER, ty * TILE + qy * QUARTER);
                    let (x1, y1) = ((x0 + QUARTER - 1).min(size - 1), (y0 + QUARTER - 1).min(size - 1));
                    if x0 >= size || y0 >= size || b[0] > x1 || b[2] < x0 || b[1] > y1 || b[3] < y0 {
                        continue;
                    }
                    boxed += 1;
                    masked += (mask >> q & 1) as u64;
                    let mut hits = 0u64;
                    for y in y0..=y1 {
                        for x in x0..=x1 {
                            hits +=
                                (rho(p, i, x as f32 + 0.5, y as f32 + 0.5, filter_inv_square) <= p.rho_max(i)) as u64;
                        }
                    }
                    reached += (hits > 0) as u64;
                    pixels_reached += hits;
                }
            }
        }
    }
    println!(
        "quarter lists: {boxed} (quarter, candidate) pairs by box, {masked} by box and footprint mask, {reached} reach a pixel of their quarter ({:.1} % of the box's, {:.1} % of the listed), {:.1} of a quarter's 64 pixels per reaching pair",
        100.0 * reached as f64 / boxed.max(1) as f64,
        100.0 * reached as f64 / masked.max(1) as f64,
        pixels_reached as f64 / reached.max(1) as f64
    );
}

/// ρ = min(ρ₃, ρ₂) at pixel centre (x, y), as the compositor computes it (f32).
fn rho(p: &raster::project::Projected, i: usize, x: f32, y: f32, filter_inv_square: f32) -> f32 {
    let (tu, tv, tw) = (p.tu(i), p.tv(i), p.tw(i));
    let k = [x * tw[0] - tu[0], x * tw[1] - tu[1], x * tw[2] - tu[2]];
    let l = [y * tw[0] - tv[0], y * tw[1] - tv[1], y * tw[2] - tv[2]];
    let h = [k[1] * l[2] - k[2] * l[1], k[2] * l[0] - k[0] * l[2], k[0] * l[1] - k[1] * l[0]];
    let (u, v) = (h[0] / h[2], h[1] / h[2]);
    let (dx, dy) = (p.mean2d(i)[0] - x, p.mean2d(i)[1] - y);
    (u * u + v * v).min(filter_inv_square * (dx * dx + dy * dy))
}

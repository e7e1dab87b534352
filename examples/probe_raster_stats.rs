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

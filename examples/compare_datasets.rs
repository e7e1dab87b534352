//! Diagnostic: how two renders of the same scene and test cameras differ, e.g. the shared
//! Cycles dataset against `radiogs synth --scene cornell --test-cameras DATA --envmap …` (our
//! shading model on the exact geometry). Per test view, under the first dataset's mask
//! (alpha > 0.5): the sRGB PSNR of B against A and the ratio of B's mean linear radiance to
//! A's per channel; then the means over the views.
//!
//!     cargo run --release --example compare_datasets -- A B
//!
//! Views are paired by name (`test_000`, …); a view missing from B is an error.

use anyhow::Context;
use radiogs::io::dataset::Dataset;
use radiogs::io::image::srgb_to_linear;
use std::path::PathBuf;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    anyhow::ensure!(args.len() == 3, "usage: compare_datasets A B");
    let (a_root, b_root) = (PathBuf::from(&args[1]), PathBuf::from(&args[2]));
    let a = Dataset::open(&a_root).with_context(|| a_root.display().to_string())?;
    let b = Dataset::open(&b_root).with_context(|| b_root.display().to_string())?;
    let (mut psnr_sum, mut ratio_sum, mut n) = (0.0f64, [0.0f64; 3], 0usize);
    println!("view        PSNR (sRGB)   B/A mean linear R G B");
    for va in &a.test {
        let name = &va.camera.name;
        let vb = b.test.iter().find(|v| &v.camera.name == name).with_context(|| format!("{name}: not in B"))?;
        let (ia, ib) = (va.load_image()?, vb.load_image()?);
        anyhow::ensure!(
            (ia.width, ia.height) == (ib.width, ib.height),
            "{name}: A is {}×{}, B {}×{}",
            ia.width,
            ia.height,
            ib.width,
            ib.height
        );
        let (mut se, mut count) = (0.0f64, 0usize);
        let (mut sum_a, mut sum_b) = ([0.0f64; 3], [0.0f64; 3]);
        for (pa, pb) in ia.data.chunks_exact(ia.channels).zip(ib.data.chunks_exact(ib.channels)) {
            if ia.channels < 4 || pa[3] <= 0.5 {
                continue;
            }
            count += 1;
            for c in 0..3 {
                se += ((pa[c] - pb[c]) as f64).powi(2);
                sum_a[c] += srgb_to_linear(pa[c]) as f64;
                sum_b[c] += srgb_to_linear(pb[c]) as f64;
            }
        }
        anyhow::ensure!(count > 0, "{name}: A's mask is empty");
        let psnr = -10.0 * (se / (3 * count) as f64).log10();
        let ratio: [f64; 3] = std::array::from_fn(|c| sum_b[c] / sum_a[c].max(1e-12));
        println!("{name:10} {psnr:8.2} dB   {:.3} {:.3} {:.3}", ratio[0], ratio[1], ratio[2]);
        psnr_sum += psnr;
        for c in 0..3 {
            ratio_sum[c] += ratio[c];
        }
        n += 1;
    }
    let k = n as f64;
    println!(
        "mean       {:8.2} dB   {:.3} {:.3} {:.3}  ({n} views)",
        psnr_sum / k,
        ratio_sum[0] / k,
        ratio_sum[1] / k,
        ratio_sum[2] / k
    );
    Ok(())
}

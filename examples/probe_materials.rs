//! Diagnostic: a run's learned albedo and roughness per object face against the dataset's
//! materials. Surfels within 15 mm of a true surface with opacity > 0.3 are grouped by their
//! nearest object and, for boxes, by the face nearest them (±x, ±y, ±z in the object frame);
//! each group prints its share of the weight (opacity × disk area), the weighted mean linear
//! albedo, the truth (the base colour at the surfel), their ratio per channel, and the mean
//! roughness against the truth. Faces of one material whose ratios differ show the light
//! (which lights them differently) absorbing what the albedo should carry.
//!
//!     cargo run --release --example probe_materials -- RUN DATA

#[path = "common/probe_run.rs"]
mod probe_run;
#[path = "common/scene_readme.rs"]
mod scene_readme;

use scene_readme::Shape;

#[derive(Default, Clone)]
struct GroupSums {
    weight: f64,
    count: usize,
    albedo: [f64; 3],
    truth: [f64; 3],
    roughness: f64,
    /// The SH colour's DC part (sRGB-like, as rasterised).
    colour: [f64; 3],
}

fn main() -> anyhow::Result<()> {
    let probe_run::ProbeRun { data, surfels, .. } = probe_run::from_args("probe_materials")?;
    let readme = scene_readme::load(&data)?;
    let objects = &readme.objects;
    if objects.is_empty() {
        anyhow::bail!("{}: README.json lists no objects", data.display());
    }
    const FACES: [&str; 6] = ["+x", "-x", "+y", "-y", "+z", "-z"];
    let mut groups = vec![GroupSums::default(); objects.len() * 6];
    for i in 0..surfels.len() {
        let m = surfels.means[i];
        let p = [m[0] as f64, m[1] as f64, m[2] as f64];
        let k = scene_readme::nearest(objects, p);
        let object = &objects[k];
        if object.sdf(p).abs() > 0.015 || surfels.opacity(i) < 0.3 {
            continue;
        }
        let truth = object.base_colour(&readme.materials[&object.material], p);
        let face = match object.shape()? {
            Shape::Cuboid { half } => {
                // The face whose plane is nearest: the axis with the largest |q| − half.
                let q = [p[0] - object.location[0], p[1] - object.location[1], p[2] - object.location[2]];
                let axis =
                    (0..3).max_by(|&a, &b| (q[a].abs() - half[a]).total_cmp(&(q[b].abs() - half[b]))).unwrap_or(0);
                2 * axis + usize::from(q[axis] < 0.0)
            }
            // A textured object (the checker floor) splits by its truth's brightness, so a
            // compressed contrast between its two colours shows.
            _ if object.textured(&readme.materials[&object.material]) => {
                usize::from(truth[0] + truth[1] + truth[2] < 1.8)
            }
            _ => 0,
        };
        let s = surfels.scale(i);
        let w = surfels.opacity(i) as f64 * (s[0] * s[1]) as f64;
        let a = surfels.albedo(i);
        let g = &mut groups[k * 6 + face];
        g.weight += w;
        g.count += 1;
        for c in 0..3 {
            g.albedo[c] += w * a[c] as f64;
            g.truth[c] += w * truth[c];
        }
        g.roughness += w * surfels.roughness(i) as f64;
        let dc = surfels.sh[i][0];
        for c in 0..3 {
            g.colour[c] += w * (dc[c] * radiogs::sh::SH_C0 + 0.5).max(0.0) as f64;
        }
    }
    let total: f64 = groups.iter().map(|g| g.weight).sum();
    println!(
        "{:<20} {:>4} {:>6} {:>6}  {:<20} {:<20} {:<20} {:>5} {:>5}  {:<20} {:<20}",
        "object",
        "face",
        "weight",
        "surfels",
        "albedo (linear)",
        "truth",
        "ours / truth",
        "rough",
        "true",
        "SH colour (DC)",
        "its chromaticity"
    );
    for (k, object) in objects.iter().enumerate() {
        let true_rough = readme.materials[&object.material].roughness;
        for (f, face) in FACES.iter().enumerate() {
            let g = &groups[k * 6 + f];
            if g.count == 0 {
                continue;
            }
            let mean = |v: [f64; 3]| v.map(|x| x / g.weight);
            let (a, t) = (mean(g.albedo), mean(g.truth));
            let fmt = |v: [f64; 3]| format!("{:.3} {:.3} {:.3}", v[0], v[1], v[2]);
            let face = match object.shape()? {
                Shape::Cuboid { .. } => *face,
                _ if object.textured(&readme.materials[&object.material]) => ["light", "dark"][f],
                _ => "all",
            };
            println!(
                "{:<20} {:>4} {:>5.1}% {:>7}  {:<20} {:<20} {:<20} {:>5.2} {:>5.2}  {:<20} {:<20}",
                object.object,
                face,
                100.0 * g.weight / total,
                g.count,
                fmt(a),
                fmt(t),
                fmt([a[0] / t[0], a[1] / t[1], a[2] / t[2]]),
                g.roughness / g.weight,
                true_rough,
                fmt(mean(g.colour)),
                fmt(chromaticity(mean(g.colour)))
            );
        }
    }
    Ok(())
}

/// c / (r + g + b): the colour without its brightness.
fn chromaticity(c: [f64; 3]) -> [f64; 3] {
    let sum = (c[0] + c[1] + c[2]).max(1e-9);
    c.map(|x| x / sum)
}

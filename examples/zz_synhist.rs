use std::path::PathBuf;
fn main() -> anyhow::Result<()> {
    let a: Vec<String> = std::env::args().collect();
    let (run, data) = (PathBuf::from(&a[1]), PathBuf::from(&a[2]));
    let v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(data.join("README.json"))?)?;
    let objs = v["objects"].as_array().unwrap();
    let s = radiogs::eval::load_run_surfels(&run)?;
    let sdf = |o: &serde_json::Value, p: [f64; 3]| -> f64 {
        let sh = &o["shape"];
        let c: Vec<f64> = sh["center"].as_array().unwrap().iter().map(|x| x.as_f64().unwrap()).collect();
        match sh["type"].as_str().unwrap() {
            "sphere" => {
                ((p[0] - c[0]).powi(2) + (p[1] - c[1]).powi(2) + (p[2] - c[2]).powi(2)).sqrt()
                    - sh["radius"].as_f64().unwrap()
            }
            "disc" => {
                let r = ((p[0] - c[0]).powi(2) + (p[1] - c[1]).powi(2)).sqrt();
                if r < sh["radius"].as_f64().unwrap() { p[2] - c[2] } else { 1e9 }
            }
            _ => 1e9,
        }
    };
    let mut hist = vec![[0f64; 16]; objs.len()];
    for i in 0..s.len() {
        let p = s.means[i].map(|x| x as f64);
        let (k, d) = objs
            .iter()
            .enumerate()
            .map(|(k, o)| (k, sdf(o, p)))
            .min_by(|a, b| a.1.abs().total_cmp(&b.1.abs()))
            .unwrap();
        let b = ((d + 0.040) / 0.005).floor();
        if b < 0.0 || b >= 16.0 {
            continue;
        }
        hist[k][b as usize] += radiogs::surfels::sigmoid(s.opacity_logits[i]) as f64;
    }
    println!(
        "signed distance bins (mm): {}",
        (0..16).map(|b| format!("{:>5}", -40 + 5 * b)).collect::<Vec<_>>().join("")
    );
    for (k, o) in objs.iter().enumerate() {
        println!(
            "{:14}            {}",
            o["name"].as_str().unwrap(),
            hist[k].iter().map(|v| format!("{:5.0}", v)).collect::<Vec<_>>().join("")
        );
    }
    Ok(())
}

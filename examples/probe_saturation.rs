//! How many covered training pixels are clipped at 1 (any channel stored as 255)? Those are
//! what `--clip-saturated` treats as lower bounds.
//! `cargo run --release --example probe_saturation -- DATA`
use radiogs::io::image::read_rgba;
use std::path::Path;

fn main() {
    let data = std::env::args().nth(1).expect("DATA");
    let (mut covered, mut clipped, mut clipped_ch) = (0usize, 0usize, [0usize; 3]);
    let mut worst = (0.0f64, String::new());
    for k in 0..200 {
        let p = format!("{data}/train_{k:03}/rgba.png");
        if !Path::new(&p).exists() {
            break;
        }
        let img = read_rgba(Path::new(&p)).unwrap();
        let (mut c, mut s) = (0, 0);
        for px in img.data.chunks(4) {
            if px[3] < 0.99 {
                continue;
            }
            c += 1;
            let mut any = false;
            for ch in 0..3 {
                if px[ch] >= 1.0 {
                    clipped_ch[ch] += 1;
                    any = true;
                }
            }
            s += any as usize;
        }
        covered += c;
        clipped += s;
        let frac = s as f64 / c.max(1) as f64;
        if frac > worst.0 {
            worst = (frac, p.clone());
        }
    }
    println!(
        "covered {covered}, clipped {clipped} ({:.3} %), per channel {:?}, worst view {:.3} % {}",
        100.0 * clipped as f64 / covered as f64,
        clipped_ch,
        100.0 * worst.0,
        worst.1
    );
}

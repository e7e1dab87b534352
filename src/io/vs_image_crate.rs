//! Temporary: the hand-written PNG / RGBE paths against the `image` crate they replace, on
//! varied inputs; floats compared bit for bit, files byte for byte. Removed with the crate.

use crate::io::image::{Image, read_rgba, write_image};
use crate::io::rgbe;
use std::io::Cursor;
use std::path::{Path, PathBuf};

struct Rng(u64);
impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        self.0 >> 16
    }
    fn byte(&mut self) -> u8 {
        (self.next() >> 8) as u8
    }
    fn unit(&mut self) -> f32 {
        (self.next() >> 24) as f32 / (1u64 << 24) as f32
    }
}

const WIDTHS: [u32; 5] = [1, 7, 8, 100, 300];

fn dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("radiogs-vs-image-{name}-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

fn image_rgba(bytes: &[u8], format: image::ImageFormat) -> Vec<f32> {
    image::load_from_memory_with_format(bytes, format).unwrap().to_rgba32f().into_raw()
}

/// The old writer: the `image` crate's PNG and HDR encoders on the same 8-bit / float buffers.
fn image_encode(img: &Image, format: image::ImageFormat) -> Vec<u8> {
    let (w, h) = (img.width, img.height);
    let to8 = |v: f32| (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8;
    let dynamic = match (format, img.channels) {
        (image::ImageFormat::Hdr, _) => {
            let rgb: Vec<f32> = img
                .data
                .chunks_exact(img.channels)
                .flat_map(|p| if p.len() < 3 { [p[0]; 3] } else { [p[0], p[1], p[2]] })
                .collect();
            image::DynamicImage::ImageRgb32F(image::Rgb32FImage::from_raw(w, h, rgb).unwrap())
        }
        (_, 1) => image::DynamicImage::ImageLuma8(
            image::GrayImage::from_raw(w, h, img.data.iter().map(|&v| to8(v)).collect()).unwrap(),
        ),
        (_, 2) => image::DynamicImage::ImageLumaA8(
            image::GrayAlphaImage::from_raw(w, h, img.data.iter().map(|&v| to8(v)).collect()).unwrap(),
        ),
        (_, 3) => image::DynamicImage::ImageRgb8(
            image::RgbImage::from_raw(w, h, img.data.iter().map(|&v| to8(v)).collect()).unwrap(),
        ),
        _ => image::DynamicImage::ImageRgba8(
            image::RgbaImage::from_raw(w, h, img.take_channels(4).data.iter().map(|&v| to8(v)).collect()).unwrap(),
        ),
    };
    let mut bytes = Vec::new();
    dynamic.write_to(&mut Cursor::new(&mut bytes), format).unwrap();
    bytes
}

/// A PNG of any colour type / bit depth, random samples (full palettes, optional tRNS and
/// gAMA + sRGB chunks, which neither reader may apply).
fn random_png(rng: &mut Rng, w: u32, h: u32, colour: png::ColorType, depth: png::BitDepth, trns: bool) -> Vec<u8> {
    let mut bytes = Vec::new();
    let mut enc = png::Encoder::new(&mut bytes, w, h);
    enc.set_color(colour);
    enc.set_depth(depth);
    let d = depth as usize;
    if colour == png::ColorType::Indexed {
        enc.set_palette((0..3 << d).map(|_| rng.byte()).collect::<Vec<u8>>());
    }
    if trns {
        let n = match colour {
            png::ColorType::Indexed => (1 << d) / 2 + 1,
            png::ColorType::Grayscale => 2,
            _ => 6,
        };
        // Grey/RGB: the transparent sample value within the bit depth.
        let mask = if d >= 8 { 0xff } else { (1u8 << d) - 1 };
        let t: Vec<u8> = (0..n)
            .map(|i| match colour {
                png::ColorType::Indexed => rng.byte(),
                _ if i % 2 == 1 => rng.byte() & mask,
                _ => 0,
            })
            .collect();
        enc.set_trns(t);
    }
    if rng.next().is_multiple_of(2) {
        enc.set_source_gamma(png::ScaledFloat::new(0.45455));
        enc.set_source_srgb(png::SrgbRenderingIntent::Perceptual);
    }
    let mut writer = enc.write_header().unwrap();
    let row = (w as usize * colour.samples() * d).div_ceil(8);
    let mut data: Vec<u8> = (0..row * h as usize).map(|_| rng.byte()).collect();
    // Some flat stretches and the extremes.
    for (i, v) in data.iter_mut().enumerate() {
        match i % 11 {
            0 => *v = 0,
            1 => *v = 255,
            _ => {}
        }
    }
    writer.write_image_data(&data).unwrap();
    writer.finish().unwrap();
    bytes
}

#[test]
fn png_reader_gives_the_image_crates_floats() {
    use png::BitDepth::*;
    use png::ColorType::*;
    let cases = [
        (Grayscale, vec![One, Two, Four, Eight, Sixteen]),
        (GrayscaleAlpha, vec![Eight, Sixteen]),
        (Rgb, vec![Eight, Sixteen]),
        (Rgba, vec![Eight, Sixteen]),
        (Indexed, vec![One, Two, Four, Eight]),
    ];
    let dir = dir("png");
    let mut rng = Rng(7);
    let mut count = 0;
    for (colour, depths) in &cases {
        for &depth in depths {
            let trns_options: &[bool] = if matches!(colour, GrayscaleAlpha | Rgba) { &[false] } else { &[false, true] };
            for &trns in trns_options {
                for w in WIDTHS {
                    let h = 1 + (rng.next() % 5) as u32;
                    let bytes = random_png(&mut rng, w, h, *colour, depth, trns);
                    let path = dir.join("a.png");
                    std::fs::write(&path, &bytes).unwrap();
                    let ours = read_rgba(&path).unwrap();
                    let theirs = image_rgba(&bytes, image::ImageFormat::Png);
                    assert_eq!((ours.width, ours.height, ours.channels), (w, h, 4));
                    if bits(&ours.data) != bits(&theirs) {
                        let i = ours.data.iter().zip(&theirs).position(|(a, b)| a.to_bits() != b.to_bits()).unwrap();
                        panic!(
                            "{colour:?} {depth:?} trns {trns} width {w} h {h}: at {i}: {} vs {}; {:?} {:?}",
                            ours.data[i],
                            theirs[i],
                            &ours.data[..16.min(ours.data.len())],
                            &theirs[..16.min(theirs.len())]
                        );
                    }
                    assert_eq!(crate::io::image::check_image(&path).unwrap(), (w, h));
                    assert_eq!(crate::io::image::image_dimensions(&path).unwrap(), (w, h));
                    count += 1;
                }
            }
        }
    }
    assert_eq!(count, 5 * (2 * 5 + 2 + 2 * 2 + 2 + 2 * 4));
    std::fs::remove_dir_all(&dir).unwrap();
}

fn random_image(rng: &mut Rng, w: u32, h: u32, channels: usize, hdr: bool) -> Image {
    let mut img = Image::new(w, h, channels);
    for v in &mut img.data {
        *v = match rng.next() % 10 {
            0 => 0.0,
            1 => 2f32.powi((rng.next() % 100) as i32 - 50),
            // Just below a power of two, where log2 may round up.
            2 => f32::from_bits(2f32.powi((rng.next() % 60) as i32 - 30).to_bits() - 1 - (rng.next() % 3) as u32),
            3 => -rng.unit(),
            4 if !hdr => rng.unit() * 1.4 - 0.2,
            _ if hdr => 10f32.powf(rng.unit() * 35.0 - 30.0),
            _ => rng.unit(),
        };
        // A few repeats so run-length paths are taken.
        if rng.next().is_multiple_of(4) {
            *v = 0.25;
        }
    }
    img
}

#[test]
fn png_writer_gives_the_image_crates_bytes() {
    let dir = dir("png-out");
    let mut rng = Rng(11);
    for channels in 1..=5 {
        for w in WIDTHS {
            let img = random_image(&mut rng, w, 3, channels, false);
            let path = dir.join("b.png");
            write_image(&path, &img).unwrap();
            let ours = std::fs::read(&path).unwrap();
            let theirs = image_encode(&img, image::ImageFormat::Png);
            assert!(ours == theirs, "{channels} channels, width {w}");
        }
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn rgbe_writer_gives_the_image_crates_bytes() {
    let dir = dir("hdr-out");
    let mut rng = Rng(13);
    for channels in [1, 3, 4] {
        for w in WIDTHS.into_iter().chain([127, 128, 129, 255, 256, 1000]) {
            let img = random_image(&mut rng, w, 4, channels, true);
            let path = dir.join("c.hdr");
            write_image(&path, &img).unwrap();
            let ours = std::fs::read(&path).unwrap();
            let theirs = image_encode(&img, image::ImageFormat::Hdr);
            assert!(ours == theirs, "{channels} channels, width {w}");
            // And both read back alike.
            let back = read_rgba(&path).unwrap();
            assert!(bits(&back.data) == bits(&image_rgba(&ours, image::ImageFormat::Hdr)), "width {w}");
        }
    }
    // Many single values, column by column (width 1: flat pixels).
    let mut values: Vec<f32> = (0..200_000).map(|_| 10f32.powf(rng.unit() * 36.0 - 31.0)).collect();
    for k in -126..127 {
        let p = 2f32.powi(k);
        values.extend([p, f32::from_bits(p.to_bits() - 1), f32::from_bits(p.to_bits() + 1), p * 1.5]);
    }
    let img = Image { width: 1, height: values.len() as u32, channels: 1, data: values };
    let path = dir.join("d.hdr");
    write_image(&path, &img).unwrap();
    assert!(std::fs::read(&path).unwrap() == image_encode(&img, image::ImageFormat::Hdr));
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn rgbe_reader_gives_the_image_crates_floats() {
    let dir = dir("hdr-in");
    let path = dir.join("e.hdr");
    // Every mantissa with every exponent, flat (no pixel is a run marker or the RLE marker).
    let mut bytes = b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 256 +X 256\n".to_vec();
    for e in 0..=255u8 {
        for m in 0..=255u8 {
            bytes.extend([m, 255 - m, m / 2, e]);
        }
    }
    std::fs::write(&path, &bytes).unwrap();
    let ours = read_rgba(&path).unwrap();
    assert!(bits(&ours.data) == bits(&image_rgba(&bytes, image::ImageFormat::Hdr)));
    // Random flat files with old-style runs (not in the first column), several widths.
    let mut rng = Rng(17);
    for w in WIDTHS {
        let h = 6;
        let mut bytes =
            format!("#?RADIANCE\n# comment\nFORMAT=32-bit_rle_rgbe\nEXPOSURE=1.5\n\n-Y {h} +X {w}\n").into_bytes();
        for _y in 0..h {
            let (mut x, mut after_run) = (0, false);
            while x < w as usize {
                // Not first in a line, not right after another marker (that would count 256-fold).
                let run = rng.next().is_multiple_of(6) && x > 0 && !after_run;
                after_run = run;
                let left = w as usize - x;
                if run {
                    let n = 1 + (rng.next() as usize % left.min(255));
                    bytes.extend([1, 1, 1, n as u8]);
                    x += n;
                } else {
                    let mut p = [rng.byte(), rng.byte(), rng.byte(), rng.byte()];
                    if p[..3] == [1, 1, 1] || (p[0] == 2 && p[1] == 2) {
                        p[0] = 9;
                    }
                    bytes.extend(p);
                    x += 1;
                }
            }
        }
        std::fs::write(&path, &bytes).unwrap();
        let ours = read_rgba(&path).unwrap();
        assert!(bits(&ours.data) == bits(&image_rgba(&bytes, image::ImageFormat::Hdr)), "width {w}");
        assert_eq!(crate::io::image::image_dimensions(&path).unwrap(), (w, h));
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn rgbe_deliberate_differences_are_where_the_image_crate_wraps() {
    // Maxima below 2^-127: the image crate wraps the exponent byte (a huge value comes back);
    // here they are black.
    let tiny = Image { width: 1, height: 1, channels: 3, data: vec![1e-39, 0.0, 0.0] };
    let theirs = image_encode(&tiny, image::ImageFormat::Hdr);
    let back = image_rgba(&theirs, image::ImageFormat::Hdr);
    assert!(back[0] > 1.0, "{back:?}");
    let ours = rgbe::encode(Path::new("t.hdr"), &tiny).unwrap();
    assert_eq!(&ours[ours.len() - 4..], [0, 0, 0, 0]);
}

#[test]
fn png_reader_matches_for_every_sample_value() {
    let dir = dir("png-all");
    let path = dir.join("all.png");
    for (colour, samples) in [
        (png::ColorType::Grayscale, 1),
        (png::ColorType::GrayscaleAlpha, 2),
        (png::ColorType::Rgb, 3),
        (png::ColorType::Rgba, 4),
    ] {
        for depth in [png::BitDepth::Eight, png::BitDepth::Sixteen] {
            // Every value in every channel: 65536 pixels, sample k of pixel p is (p + k·97) mod 2^d.
            let values = if depth == png::BitDepth::Eight { 256 } else { 65536 };
            let mut data = Vec::new();
            for p in 0..65536usize {
                for k in 0..samples {
                    let v = (p + k * 97) % values;
                    if depth == png::BitDepth::Eight {
                        data.push(v as u8);
                    } else {
                        data.extend((v as u16).to_be_bytes());
                    }
                }
            }
            let mut bytes = Vec::new();
            let mut enc = png::Encoder::new(&mut bytes, 256, 256);
            enc.set_color(colour);
            enc.set_depth(depth);
            let mut writer = enc.write_header().unwrap();
            writer.write_image_data(&data).unwrap();
            writer.finish().unwrap();
            std::fs::write(&path, &bytes).unwrap();
            let ours = read_rgba(&path).unwrap();
            assert!(bits(&ours.data) == bits(&image_rgba(&bytes, image::ImageFormat::Png)), "{colour:?} {depth:?}");
        }
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

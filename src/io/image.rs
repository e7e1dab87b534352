//! Float images and their files: PNG (8/16-bit, sRGB-encoded as stored), OpenEXR and Radiance
//! .hdr (linear). Every reader names the file in its error; every writer is atomic.

use crate::error::{Error, Result};
use crate::io::atomic::write_atomic;
use std::path::Path;

/// An interleaved float image, row-major from the top row.
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    pub width: u32,
    pub height: u32,
    pub channels: usize,
    pub data: Vec<f32>,
}

impl Image {
    pub fn new(width: u32, height: u32, channels: usize) -> Image {
        Image { width, height, channels, data: vec![0.0; width as usize * height as usize * channels] }
    }
    pub fn pixel(&self, x: u32, y: u32) -> &[f32] {
        let i = (y as usize * self.width as usize + x as usize) * self.channels;
        &self.data[i..i + self.channels]
    }
    pub fn pixel_mut(&mut self, x: u32, y: u32) -> &mut [f32] {
        let i = (y as usize * self.width as usize + x as usize) * self.channels;
        &mut self.data[i..i + self.channels]
    }
    pub fn pixel_count(&self) -> usize {
        self.width as usize * self.height as usize
    }
    /// Keep only the first `n` channels.
    pub fn take_channels(&self, n: usize) -> Image {
        let n = n.min(self.channels);
        let mut out = Image::new(self.width, self.height, n);
        for (dst, src) in out.data.chunks_exact_mut(n).zip(self.data.chunks_exact(self.channels)) {
            dst.copy_from_slice(&src[..n]);
        }
        out
    }
    /// Shrink by an integer `factor`: each output pixel is the mean of a factor × factor block
    /// (the right and bottom `size mod factor` pixels, which fill no block, are dropped, so
    /// output pixel j covers exactly input pixels [j·factor, (j + 1)·factor) and a camera
    /// scales by 1/factor). With 4 channels the colour is averaged weighted by alpha (straight
    /// alpha: a half-covered edge pixel keeps the object's colour) and alpha is averaged;
    /// values are averaged as stored (PNG sRGB-encoded, as PIL's resize in 3DGS/2DGS).
    pub fn downscale(&self, factor: u32) -> Image {
        let f = factor.max(1);
        if f == 1 {
            return self.clone();
        }
        let (w, h, c) = ((self.width / f) as usize, (self.height / f) as usize, self.channels);
        let fu = f as usize;
        let mut out = Image::new(w as u32, h as u32, c);
        let inv = 1.0 / (fu * fu) as f64;
        let mut sum = vec![0.0f64; c];
        for y in 0..h {
            for x in 0..w {
                sum.iter_mut().for_each(|v| *v = 0.0);
                let mut alpha_weighted = [0.0f64; 3];
                for sy in y * fu..(y + 1) * fu {
                    let row = sy * self.width as usize;
                    for sx in x * fu..(x + 1) * fu {
                        let px = &self.data[(row + sx) * c..(row + sx + 1) * c];
                        for (acc, &v) in sum.iter_mut().zip(px) {
                            *acc += v as f64;
                        }
                        if c == 4 {
                            for k in 0..3 {
                                alpha_weighted[k] += px[k] as f64 * px[3] as f64;
                            }
                        }
                    }
                }
                let dst = out.pixel_mut(x as u32, y as u32);
                for k in 0..c {
                    dst[k] = (sum[k] * inv) as f32;
                }
                if c == 4 && sum[3] > 0.0 {
                    for k in 0..3 {
                        dst[k] = (alpha_weighted[k] / sum[3]) as f32;
                    }
                }
            }
        }
        out
    }
    /// Apply `f` to every value of the first `n` channels (e.g. colour but not alpha).
    pub fn map_channels(&mut self, n: usize, f: impl Fn(f32) -> f32) {
        let c = self.channels;
        for px in self.data.chunks_exact_mut(c) {
            for v in &mut px[..n.min(c)] {
                *v = f(*v);
            }
        }
    }
}

/// sRGB OETF (linear → encoded), clamped to [0, 1].
pub fn linear_to_srgb(x: f32) -> f32 {
    let x = x.clamp(0.0, 1.0);
    if x <= 0.003_130_8 { 12.92 * x } else { 1.055 * x.powf(1.0 / 2.4) - 0.055 }
}

/// Derivative of [`linear_to_srgb`] (zero where clamped).
pub fn linear_to_srgb_derivative(x: f32) -> f32 {
    if x <= 0.0 || x >= 1.0 {
        0.0
    } else if x <= 0.003_130_8 {
        12.92
    } else {
        1.055 / 2.4 * x.powf(1.0 / 2.4 - 1.0)
    }
}

/// sRGB EOTF (encoded → linear).
pub fn srgb_to_linear(x: f32) -> f32 {
    if x <= 0.040_45 { x / 12.92 } else { ((x + 0.055) / 1.055).powf(2.4) }
}

fn decode_error(path: &Path, e: image::ImageError) -> Error {
    match e {
        // Decoders read from memory: running out of bytes means the file ends early.
        image::ImageError::IoError(io) if io.kind() == std::io::ErrorKind::UnexpectedEof => {
            Error::format(path, "image data", "the file ends early (truncated or empty)")
        }
        image::ImageError::IoError(io) => Error::io(path, io),
        other => Error::format(path, "image data", other.to_string()),
    }
}

fn open(path: &Path) -> Result<image::DynamicImage> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    let format = image::ImageFormat::from_path(path)
        .map_err(|_| Error::format(path, "extension", "not a known image type (png, exr, hdr)"))?;
    image::load_from_memory_with_format(&bytes, format).map_err(|e| decode_error(path, e))
}

/// Read named channels of an OpenEXR file's first layer (e.g. `["R", "G", "B"]`, or
/// `["diffuse_indirect.R", ...]`). A name that is absent is an error naming it.
pub fn read_exr_channels(path: &Path, names: &[&str]) -> Result<Image> {
    let image = exr::prelude::read_first_flat_layer_from_file(path).map_err(|e| match e {
        exr::error::Error::Io(io) => Error::io(path, io),
        other => Error::format(path, "OpenEXR data", other.to_string()),
    })?;
    let layer = &image.layer_data;
    let (width, height) = (layer.size.0, layer.size.1);
    let mut out = Image::new(width as u32, height as u32, names.len());
    for (c, name) in names.iter().enumerate() {
        let channel = layer
            .channel_data
            .list
            .iter()
            .find(|ch| ch.name.to_string() == *name)
            .ok_or_else(|| Error::format(path, format!("channel {name}"), "missing"))?;
        for i in 0..width * height {
            out.data[i * names.len() + c] = channel.sample_data.value_by_flat_index(i).to_f32();
        }
    }
    Ok(out)
}

/// Names of the channels of an OpenEXR file's first layer.
pub fn exr_channel_names(path: &Path) -> Result<Vec<String>> {
    let meta = exr::meta::MetaData::read_from_file(path, false)
        .map_err(|e| Error::format(path, "OpenEXR header", e.to_string()))?;
    let header = meta.headers.first().ok_or_else(|| Error::format(path, "OpenEXR header", "no layer"))?;
    Ok(header.channels.list.iter().map(|c| c.name.to_string()).collect())
}

/// Read an EXR as RGBA: channels R,G,B[,A], or X,Y,Z[,A] (vectors such as normals), or a
/// single Y/Z/V channel repeated (depth); missing alpha becomes 1.
fn read_exr_rgba(path: &Path) -> Result<Image> {
    let names = exr_channel_names(path)?;
    let has = |n: &str| names.iter().any(|x| x == n);
    let alpha = has("A");
    let colour: Vec<&str> = if has("R") && has("G") && has("B") {
        vec!["R", "G", "B"]
    } else if has("X") && has("Y") && has("Z") {
        vec!["X", "Y", "Z"]
    } else if let Some(single) = ["Y", "Z", "V", "R", "depth.V", "depth.Z"].into_iter().find(|n| has(n)) {
        vec![single, single, single]
    } else {
        return Err(Error::format(path, "channels", format!("no R,G,B or X,Y,Z channels among {names:?}")));
    };
    let mut wanted = colour;
    if alpha {
        wanted.push("A");
    }
    let img = read_exr_channels(path, &wanted)?;
    if alpha { Ok(img) } else { Ok(expand_to(&img, 4)) }
}

/// Read any supported image as RGBA float. PNG values are scaled to [0, 1] and left
/// encoded as stored (sRGB for colour); EXR/HDR are linear. Missing alpha becomes 1.
pub fn read_rgba(path: &Path) -> Result<Image> {
    let is_exr = path.extension().is_some_and(|e| e.eq_ignore_ascii_case("exr"));
    let (width, height, data) = if is_exr {
        let img = read_exr_rgba(path)?;
        (img.width, img.height, img.data)
    } else {
        let rgba = open(path)?.to_rgba32f();
        let (width, height) = rgba.dimensions();
        (width, height, rgba.into_raw())
    };
    if let Some(bad) = data.iter().position(|v| !v.is_finite()) {
        let px = bad / 4;
        return Err(Error::format(
            path,
            format!("pixel ({}, {})", px % width as usize, px / width as usize),
            "value is NaN or infinite",
        ));
    }
    Ok(Image { width, height, channels: 4, data })
}

/// Decode an image in full and return its size, keeping no float copy: a truncated or corrupt
/// file fails here as it would in [`read_rgba`] (with the same message), at the cost of the
/// decode alone for PNG (float formats are read as [`read_rgba`] reads them, values checked).
pub fn check_image(path: &Path) -> Result<(u32, u32)> {
    if path.extension().is_some_and(|e| e.eq_ignore_ascii_case("png")) {
        let img = open(path)?;
        return Ok((img.width(), img.height()));
    }
    let img = read_rgba(path)?;
    Ok((img.width, img.height))
}

/// Read an image and keep its first `channels` channels (1 = the first/luminance channel).
pub fn read_channels(path: &Path, channels: usize) -> Result<Image> {
    Ok(read_rgba(path)?.take_channels(channels))
}

fn encode(img: &Image, format: image::ImageFormat, path: &Path) -> Result<Vec<u8>> {
    let (w, h) = (img.width, img.height);
    let mut bytes = Vec::new();
    let mut cursor = std::io::Cursor::new(&mut bytes);
    let result = match (format, img.channels) {
        (image::ImageFormat::Png, c) => {
            let to8 = |v: f32| (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8;
            match c {
                1 => image::GrayImage::from_raw(w, h, img.data.iter().map(|&v| to8(v)).collect())
                    .map(image::DynamicImage::ImageLuma8),
                2 => image::GrayAlphaImage::from_raw(w, h, img.data.iter().map(|&v| to8(v)).collect())
                    .map(image::DynamicImage::ImageLumaA8),
                3 => image::RgbImage::from_raw(w, h, img.data.iter().map(|&v| to8(v)).collect())
                    .map(image::DynamicImage::ImageRgb8),
                _ => image::RgbaImage::from_raw(w, h, img.take_channels(4).data.iter().map(|&v| to8(v)).collect())
                    .map(image::DynamicImage::ImageRgba8),
            }
            .ok_or_else(|| Error::invalid(path.display().to_string(), "image buffer has the wrong size"))?
            .write_to(&mut cursor, format)
        }
        (image::ImageFormat::Hdr, _) => {
            let rgb = expand_to(img, 3);
            image::Rgb32FImage::from_raw(w, h, rgb.data)
                .map(image::DynamicImage::ImageRgb32F)
                .ok_or_else(|| Error::invalid(path.display().to_string(), "image buffer has the wrong size"))?
                .write_to(&mut cursor, format)
        }
        (image::ImageFormat::OpenExr, _) => return encode_exr(img, path),
        _ => {
            return Err(Error::invalid(path.display().to_string(), "unsupported image format (use png, exr or hdr)"));
        }
    };
    result.map_err(|e| Error::format(path, "encoding", e.to_string()))?;
    Ok(bytes)
}

/// OpenEXR, ZIP-compressed scan lines in increasing order. The `image` crate's writer uses the
/// exr default (tiles in unspecified order, compressed in parallel), so the same picture could
/// come out as different bytes from run to run; a run's outputs must be reproducible.
fn encode_exr(img: &Image, path: &Path) -> Result<Vec<u8>> {
    use exr::prelude::{Encoding, Image as ExrImage, SpecificChannels, Vec2, WritableImage};
    let (w, h) = (img.width as usize, img.height as usize);
    let out = if img.channels == 3 { expand_to(img, 3) } else { expand_to(img, 4) };
    let n = out.channels;
    let px = |p: Vec2<usize>| &out.data[(p.y() * w + p.x()) * n..(p.y() * w + p.x() + 1) * n];
    let mut bytes = Vec::new();
    let mut cursor = std::io::Cursor::new(&mut bytes);
    let result = if n == 3 {
        let channels = SpecificChannels::rgb(|p: Vec2<usize>| {
            let v = px(p);
            (v[0], v[1], v[2])
        });
        ExrImage::from_encoded_channels((w, h), Encoding::SMALL_LOSSLESS, channels).write().to_buffered(&mut cursor)
    } else {
        let channels = SpecificChannels::rgba(|p: Vec2<usize>| {
            let v = px(p);
            (v[0], v[1], v[2], v[3])
        });
        ExrImage::from_encoded_channels((w, h), Encoding::SMALL_LOSSLESS, channels).write().to_buffered(&mut cursor)
    };
    result.map_err(|e| Error::format(path, "encoding", e.to_string()))?;
    Ok(bytes)
}

/// Grey → RGB(A), RGB → RGBA (alpha 1), or truncation, to exactly `n` channels (3 or 4).
fn expand_to(img: &Image, n: usize) -> Image {
    let mut out = Image::new(img.width, img.height, n);
    for (dst, src) in out.data.chunks_exact_mut(n).zip(img.data.chunks_exact(img.channels)) {
        let (rgb, a) = match src.len() {
            1 => ([src[0]; 3], 1.0),
            2 => ([src[0]; 3], src[1]),
            3 => ([src[0], src[1], src[2]], 1.0),
            _ => ([src[0], src[1], src[2]], src[3]),
        };
        dst[..3].copy_from_slice(&rgb);
        if n == 4 {
            dst[3] = a;
        }
    }
    out
}

/// Write an image, choosing the format from the extension (png: 8-bit, values clamped to
/// [0, 1] and written as given; exr: 32-bit float; hdr: RGBE). Atomic.
pub fn write_image(path: &Path, img: &Image) -> Result<()> {
    let format = image::ImageFormat::from_path(path)
        .map_err(|_| Error::invalid(path.display().to_string(), "unknown image extension (use png, exr or hdr)"))?;
    let bytes = encode(img, format, path)?;
    write_atomic(path, &bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn downscale_averages_blocks_weighting_colour_by_alpha() {
        // 5 × 3 RGBA by 2: a 2 × 1 result; column 4 and row 2 fill no block and are dropped.
        let mut img = Image::new(5, 3, 4);
        for y in 0..3 {
            for x in 0..5 {
                let v = (y * 5 + x) as f32;
                img.pixel_mut(x, y).copy_from_slice(&[v, 2.0 * v, 0.5, 1.0]);
            }
        }
        // Block (0, 0): pixels 0, 1, 5, 6; one of them transparent with another colour.
        img.pixel_mut(1, 0).copy_from_slice(&[100.0, 100.0, 100.0, 0.0]);
        let small = img.downscale(2);
        assert_eq!((small.width, small.height, small.channels), (2, 1, 4));
        // Colour: the three opaque pixels only; alpha: the mean of all four.
        let expect0 = [(0.0 + 5.0 + 6.0) / 3.0, 2.0 * (0.0 + 5.0 + 6.0) / 3.0, 0.5, 0.75];
        for k in 0..4 {
            assert!((small.pixel(0, 0)[k] - expect0[k]).abs() < 1e-6, "{k}: {:?}", small.pixel(0, 0));
        }
        let expect1 = [(2.0 + 3.0 + 7.0 + 8.0) / 4.0, (4.0 + 6.0 + 14.0 + 16.0) / 4.0, 0.5, 1.0];
        for k in 0..4 {
            assert!((small.pixel(1, 0)[k] - expect1[k]).abs() < 1e-5, "{k}: {:?}", small.pixel(1, 0));
        }
        // A fully transparent block keeps the plain mean (no division by zero).
        let clear = Image { width: 2, height: 2, channels: 4, data: vec![0.2, 0.4, 0.6, 0.0].repeat(4) };
        assert_eq!(clear.downscale(2).data, vec![0.2, 0.4, 0.6, 0.0]);
        // One channel: the plain mean; factor 1: the same image.
        let grey = Image { width: 2, height: 2, channels: 1, data: vec![1.0, 2.0, 3.0, 6.0] };
        assert_eq!(grey.downscale(2).data, vec![3.0]);
        assert_eq!(img.downscale(1), img);
    }

    #[test]
    fn srgb_round_trip() {
        for i in 0..=100 {
            let x = i as f32 / 100.0;
            assert!((srgb_to_linear(linear_to_srgb(x)) - x).abs() < 1e-5);
        }
    }

    #[test]
    fn png_and_exr_round_trip() {
        let dir = std::env::temp_dir().join(format!("radiogs-img-{}", std::process::id()));
        let mut img = Image::new(5, 3, 4);
        for (i, v) in img.data.iter_mut().enumerate() {
            *v = (i % 256) as f32 / 255.0;
        }
        write_image(&dir.join("a.png"), &img).unwrap();
        let back = read_rgba(&dir.join("a.png")).unwrap();
        assert_eq!(back.width, 5);
        for (a, b) in img.data.iter().zip(&back.data) {
            assert!((a - b).abs() < 1.0 / 255.0);
        }
        img.data[7] = 12.5;
        write_image(&dir.join("a.exr"), &img).unwrap();
        assert_eq!(read_rgba(&dir.join("a.exr")).unwrap(), img);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// Many blocks compressed in parallel must still give the same bytes every time (the exr
    /// default order is completion order), and read back exactly, for RGB and RGBA.
    #[test]
    fn exr_bytes_are_reproducible() {
        let path = Path::new("reproducible.exr");
        for channels in [3, 4] {
            let mut img = Image::new(96, 200, channels);
            for (i, v) in img.data.iter_mut().enumerate() {
                *v = ((i * 7919) % 1013) as f32 * 0.37;
            }
            let first = encode_exr(&img, path).unwrap();
            for _ in 0..20 {
                assert!(encode_exr(&img, path).unwrap() == first, "{channels} channels: bytes differ");
            }
            let dir = std::env::temp_dir().join(format!("radiogs-exr-{}-{channels}", std::process::id()));
            write_image(&dir.join("a.exr"), &img).unwrap();
            let back = read_rgba(&dir.join("a.exr")).unwrap();
            assert_eq!(back, expand_to(&img, 4));
            std::fs::remove_dir_all(&dir).unwrap();
        }
    }

    /// Formats the image crate knows but we do not write are refused by name, nothing written.
    #[test]
    fn unsupported_output_format_is_refused() {
        let dir = std::env::temp_dir().join(format!("radiogs-fmt-{}", std::process::id()));
        let path = dir.join("a.jpg");
        let err = write_image(&path, &Image::new(4, 4, 3)).unwrap_err().to_string();
        assert!(err.contains("a.jpg") && err.contains("png, exr or hdr"), "{err}");
        assert!(!path.exists());
    }

    #[test]
    fn truncated_png_names_the_file() {
        let dir = std::env::temp_dir().join(format!("radiogs-trunc-{}", std::process::id()));
        let img = Image::new(16, 16, 4);
        let path = dir.join("view.png");
        write_image(&path, &img).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        std::fs::write(&path, &bytes[..bytes.len() / 2]).unwrap();
        let err = read_rgba(&path).unwrap_err().to_string();
        assert!(err.contains("view.png"), "{err}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}

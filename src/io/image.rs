//! Float images and their files: PNG (8/16-bit, sRGB-encoded as stored; the `png` crate),
//! OpenEXR (the `exr` crate) and Radiance .hdr (linear; [`crate::io::rgbe`]). Every reader names
//! the file in its error; every writer is atomic.

use crate::error::{Error, Result};
use crate::io::atomic::write_atomic;
use crate::io::dataset::MAX_IMAGE_SIDE;
use crate::io::rgbe;
use std::path::{Path, PathBuf};

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
#[inline]
pub fn srgb_to_linear(x: f32) -> f32 {
    if x <= 0.040_45 { x / 12.92 } else { pow_2_4((x + 0.055) / 1.055) }
}

/// t^2.4 for t > 0 within an ulp of the exact value, without a libm call: t = 2^e·m with
/// m ∈ [1, 2), 2^(2.4e) from a table and m^2.4 from a degree-8 polynomial (Chebyshev
/// interpolation, relative error 6.5e-10), both in f64. Why: the inverse stage's tracer decodes
/// every hit's colour (millions an iteration), where glibc's powf took ≈ 3 % of the iteration.
/// Octaves outside the table (t < 2⁻⁴ or t ≥ 2⁹: no sRGB colour up to 540) use powf.
#[inline]
pub fn pow_2_4(t: f32) -> f32 {
    /// 2^(2.4 e) for e = −4..=8.
    const OCTAVES: [f64; 13] = [
        0.001288581944114155,
        0.006801176275750973,
        0.03589682359365735,
        0.18946457081379978,
        1.0,
        5.278031643091577,
        27.85761802547597,
        147.0333894396204,
        776.0468820533237,
        4096.0,
        21618.817610103077,
        114104.80343234964,
        602248.7631446852,
    ];
    /// m^2.4 = Σ_k C[k]·x^k with x = 2m − 3 ∈ [−1, 1).
    const C: [f64; 9] = [
        2.646177800680514,
        2.116942235986211,
        0.49395319047344716,
        0.02195353562783846,
        -0.0010976872049127057,
        0.00011686953061524403,
        -1.6864433494529545e-05,
        3.179866832662507e-06,
        -6.178504929405588e-07,
    ];
    let bits = t.to_bits();
    // Positive normal t: the biased exponent; 4 + e indexes the table.
    let at = (bits >> 23).wrapping_sub(127 - 4) as usize;
    // Zero, negative (sign bit set), subnormal, infinite and NaN t all land outside too.
    if at >= OCTAVES.len() {
        return t.powf(2.4);
    }
    let x = 2.0 * f32::from_bits((bits & 0x007f_ffff) | 0x3f80_0000) as f64 - 3.0;
    let mut p = C[8];
    for k in (0..8).rev() {
        p = p.mul_add(x, C[k]);
    }
    (p * OCTAVES[at]) as f32
}

/// The most pixels an image file may declare (the largest side a dataset may have, squared):
/// a corrupt or hostile header cannot make a reader allocate more.
pub const MAX_PIXELS: u64 = MAX_IMAGE_SIDE as u64 * MAX_IMAGE_SIDE as u64;

/// What every reader says when the bytes run out.
pub(crate) const TRUNCATED: &str = "the file ends early (truncated or empty)";

/// Memory the PNG decoder may use for its own buffers (the limit the `image` crate gave it).
const PNG_DECODER_LIMIT: usize = 512 << 20;

/// DEFLATE expands at most 1032-fold (a 258-byte match coded in two bits), so a PNG header
/// promising more raw bytes than that times the file's size is corrupt.
const MAX_DEFLATE_RATIO: u64 = 1032;

/// The image formats read and written, by extension (case-insensitive).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Format {
    Png,
    Exr,
    Hdr,
}

fn format_of(path: &Path) -> Option<Format> {
    let ext = path.extension()?.to_str()?.to_ascii_lowercase();
    match ext.as_str() {
        "png" | "apng" => Some(Format::Png),
        "exr" => Some(Format::Exr),
        "hdr" => Some(Format::Hdr),
        _ => None,
    }
}

fn unknown_type(path: &Path) -> Error {
    Error::format(path, "extension", "not a known image type (png, exr, hdr)")
}

fn read_bytes(path: &Path) -> Result<Vec<u8>> {
    std::fs::read(path).map_err(|e| Error::io(path, e))
}

fn png_error(path: &Path, field: &str, e: png::DecodingError) -> Error {
    match e {
        // The decoder reads from memory: running out of bytes means the file ends early.
        png::DecodingError::IoError(io) if io.kind() == std::io::ErrorKind::UnexpectedEof => {
            Error::format(path, field, TRUNCATED)
        }
        png::DecodingError::IoError(io) => Error::io(path, io),
        png::DecodingError::LimitsExceeded => {
            Error::format(path, field, "needs more memory than the PNG decoder may use")
        }
        other => Error::format(path, field, other.to_string()),
    }
}

/// Refuse a PNG header whose size is beyond [`MAX_PIXELS`] or beyond what the file's bytes
/// could hold, before any buffer of that size is allocated.
fn check_png_size(path: &Path, info: &png::Info, file_len: usize) -> Result<()> {
    let (w, h) = (info.width as u64, info.height as u64);
    if w * h > MAX_PIXELS {
        return Err(Error::format(
            path,
            "PNG header",
            format!("{w}×{h} is more than the {MAX_PIXELS} pixels an image may have"),
        ));
    }
    let raw_bytes = h * (1 + (w * info.bits_per_pixel() as u64).div_ceil(8));
    if raw_bytes > MAX_DEFLATE_RATIO * file_len as u64 {
        return Err(Error::format(path, "PNG header", format!("{w}×{h} pixels cannot fit in {file_len} bytes")));
    }
    Ok(())
}

/// A PNG decoder past the header, set to expand palettes, grey below 8 bits and tRNS to plain
/// 8- or 16-bit samples. No gamma, sRGB or ICC conversion: values are read as stored.
fn png_reader<'a>(path: &Path, bytes: &'a [u8]) -> Result<png::Reader<std::io::Cursor<&'a [u8]>>> {
    png_reader_with(path, bytes, png::Transformations::EXPAND)
}

fn png_reader_with<'a>(
    path: &Path,
    bytes: &'a [u8],
    transformations: png::Transformations,
) -> Result<png::Reader<std::io::Cursor<&'a [u8]>>> {
    let limits = png::Limits { bytes: PNG_DECODER_LIMIT };
    let mut decoder = png::Decoder::new_with_limits(std::io::Cursor::new(bytes), limits);
    decoder.set_transformations(transformations);
    let info = decoder.read_header_info().map_err(|e| png_error(path, "PNG header", e))?;
    check_png_size(path, info, bytes.len())?;
    decoder.read_info().map_err(|e| png_error(path, "image data", e))
}

/// A decoded PNG: 1–4 samples a pixel (grey, grey+alpha, RGB, RGBA), 8- or 16-bit
/// (big-endian), rows packed.
struct DecodedPng {
    width: u32,
    height: u32,
    samples: usize,
    sixteen_bit: bool,
    data: Vec<u8>,
}

/// Decode the first (or only) frame of a PNG.
fn decode_png(path: &Path, bytes: &[u8]) -> Result<DecodedPng> {
    let mut reader = png_reader(path, bytes)?;
    if reader.info().color_type == png::ColorType::Indexed {
        check_palette_indices(path, bytes)?;
    }
    let size = reader.output_buffer_size();
    let size = size.ok_or_else(|| png_error(path, "image data", png::DecodingError::LimitsExceeded))?;
    let mut data = vec![0; size];
    let frame = reader.next_frame(&mut data).map_err(|e| png_error(path, "image data", e))?;
    let sixteen_bit = match frame.bit_depth {
        png::BitDepth::Eight => false,
        png::BitDepth::Sixteen => true,
        other => return Err(Error::format(path, "image data", format!("{other:?}-bit samples after expansion"))),
    };
    let (width, height) = (frame.width, frame.height);
    Ok(DecodedPng { width, height, samples: frame.color_type.samples(), sixteen_bit, data })
}

/// A palette image's indices all name a palette entry. The decoder's expansion turns an index
/// past the palette's end into black without a word; the PNG specification calls it an error.
/// Costs a second decode, of palette images only, and only when the palette has fewer entries
/// than the bit depth can index.
fn check_palette_indices(path: &Path, bytes: &[u8]) -> Result<()> {
    let mut reader = png_reader_with(path, bytes, png::Transformations::IDENTITY)?;
    let info = reader.info();
    let entries = info.palette.as_ref().map_or(0, |p| p.len() / 3);
    let depth = info.bit_depth as usize;
    if entries >= 1 << depth {
        return Ok(());
    }
    let size = reader.output_buffer_size();
    let size = size.ok_or_else(|| png_error(path, "image data", png::DecodingError::LimitsExceeded))?;
    let mut data = vec![0; size];
    let frame = reader.next_frame(&mut data).map_err(|e| png_error(path, "image data", e))?;
    let (per_byte, mask) = (8 / depth, ((1u16 << depth) - 1) as u8);
    for y in 0..frame.height as usize {
        let row = &data[y * frame.line_size..];
        for x in 0..frame.width as usize {
            let shift = 8 - depth * (x % per_byte + 1);
            let index = (row[x / per_byte] >> shift) & mask;
            if index as usize >= entries {
                return Err(Error::format(
                    path,
                    "image data",
                    format!("pixel ({x}, {y}) has palette index {index}, but the palette has {entries} colours"),
                ));
            }
        }
    }
    Ok(())
}

/// RGBA floats in [0, 1] (v / 255 or v / 65535, as stored), grey repeated, missing alpha 1.
/// Rounded as the `image` crate's `to_rgba32f` rounded, so inputs read as before to the bit:
/// it divided RGB(A) samples but multiplied grey ones by the reciprocal (a different path), and
/// the two differ in the last bit for some values.
fn png_to_rgba(png: &DecodedPng) -> Image {
    let grey = png.samples <= 2;
    let (max, reciprocal) = if png.sixteen_bit { (65535.0, 1.0 / 65535.0) } else { (255.0, 1.0 / 255.0) };
    let sample = |i: usize| {
        let v = if png.sixteen_bit {
            u16::from_be_bytes([png.data[2 * i], png.data[2 * i + 1]]) as f32
        } else {
            png.data[i] as f32
        };
        if grey { v * reciprocal } else { v / max }
    };
    let mut out = Image::new(png.width, png.height, 4);
    for (p, dst) in out.data.chunks_exact_mut(4).enumerate() {
        let s = |k: usize| sample(p * png.samples + k);
        let rgba = match png.samples {
            1 => [s(0), s(0), s(0), 1.0],
            2 => [s(0), s(0), s(0), s(1)],
            3 => [s(0), s(1), s(2), 1.0],
            _ => [s(0), s(1), s(2), s(3)],
        };
        dst.copy_from_slice(&rgba);
    }
    out
}

/// The width and height an image file declares, from its header alone where the format
/// allows (PNG, EXR; a .hdr is read whole, its pixels left undecoded).
pub fn image_dimensions(path: &Path) -> Result<(u32, u32)> {
    match format_of(path) {
        Some(Format::Png) => {
            let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
            let mut decoder = png::Decoder::new(std::io::BufReader::new(file));
            let info = decoder.read_header_info().map_err(|e| png_error(path, "image header", e))?;
            Ok(info.size())
        }
        Some(Format::Exr) => {
            let meta = exr::meta::MetaData::read_from_file(path, false).map_err(|e| match e {
                exr::error::Error::Io(io) => Error::io(path, io),
                other => Error::format(path, "OpenEXR header", other.to_string()),
            })?;
            let header = meta.headers.first().ok_or_else(|| Error::format(path, "OpenEXR header", "no layer"))?;
            let size = header.layer_size;
            let side = |v: usize| u32::try_from(v).map_err(|_| Error::format(path, "OpenEXR header", "too large"));
            Ok((side(size.0)?, side(size.1)?))
        }
        Some(Format::Hdr) => rgbe::dimensions(path, &read_bytes(path)?),
        None => Err(unknown_type(path)),
    }
}

/// Read named channels of an OpenEXR file's first layer (e.g. `["R", "G", "B"]`, or
/// `["diffuse_indirect.R", ...]`). A name that is absent is an error naming it.
pub fn read_exr_channels(path: &Path, names: &[&str]) -> Result<Image> {
    // The header's size first: the decoder allocates whatever the data window claims.
    let (w, h) = image_dimensions(path)?;
    if w as u64 * h as u64 > MAX_PIXELS {
        return Err(Error::format(
            path,
            "OpenEXR header",
            format!("{w}×{h} is more than the {MAX_PIXELS} pixels an image may have"),
        ));
    }
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
    let img = match format_of(path) {
        Some(Format::Exr) => read_exr_rgba(path)?,
        format => {
            let bytes = read_bytes(path)?;
            match format {
                Some(Format::Png) => png_to_rgba(&decode_png(path, &bytes)?),
                Some(Format::Hdr) => expand_to(&rgbe::decode(path, &bytes)?, 4),
                _ => return Err(unknown_type(path)),
            }
        }
    };
    if let Some(bad) = img.data.iter().position(|v| !v.is_finite()) {
        let px = bad / 4;
        return Err(Error::format(
            path,
            format!("pixel ({}, {})", px % img.width as usize, px / img.width as usize),
            "value is NaN or infinite",
        ));
    }
    Ok(img)
}

/// Decode an image in full and return its size, keeping no float copy: a truncated or corrupt
/// file fails here as it would in [`read_rgba`] (with the same message), at the cost of the
/// decode alone for PNG (float formats are read as [`read_rgba`] reads them, values checked).
pub fn check_image(path: &Path) -> Result<(u32, u32)> {
    if format_of(path) == Some(Format::Png) {
        let png = decode_png(path, &read_bytes(path)?)?;
        return Ok((png.width, png.height));
    }
    let img = read_rgba(path)?;
    Ok((img.width, img.height))
}

/// Read an image and keep its first `channels` channels (1 = the first/luminance channel).
pub fn read_channels(path: &Path, channels: usize) -> Result<Image> {
    Ok(read_rgba(path)?.take_channels(channels))
}

/// 8-bit PNG of the first 1–4 channels (grey, grey+alpha, RGB, RGBA), values clamped to
/// [0, 1]. Fast compression with adaptive row filters, the `image` crate's defaults, so the
/// bytes match files it wrote; the encoder is deterministic.
fn encode_png(img: &Image, path: &Path) -> Result<Vec<u8>> {
    let samples = img.channels.min(4);
    if samples == 0 || img.data.len() != img.pixel_count() * img.channels {
        return Err(Error::invalid(path.display().to_string(), "image buffer has the wrong size"));
    }
    let colour = match samples {
        1 => png::ColorType::Grayscale,
        2 => png::ColorType::GrayscaleAlpha,
        3 => png::ColorType::Rgb,
        _ => png::ColorType::Rgba,
    };
    let to8 = |v: f32| (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8;
    let pixels: Vec<u8> = img.data.chunks_exact(img.channels).flat_map(|px| &px[..samples]).map(|&v| to8(v)).collect();
    let encoding_error = |e: png::EncodingError| Error::format(path, "encoding", e.to_string());
    let mut bytes = Vec::new();
    let mut encoder = png::Encoder::new(&mut bytes, img.width, img.height);
    encoder.set_color(colour);
    encoder.set_depth(png::BitDepth::Eight);
    encoder.set_compression(png::Compression::Fast);
    encoder.set_filter(png::Filter::Adaptive);
    let mut writer = encoder.write_header().map_err(encoding_error)?;
    writer.write_image_data(&pixels).map_err(encoding_error)?;
    writer.finish().map_err(encoding_error)?;
    Ok(bytes)
}

/// An animated PNG (APNG, looping forever at `fps` frames per second) of 8-bit PNG files of
/// one size, each frame exactly its file's pixels (read back as RGBA). Browsers and most image
/// viewers play it; others show the first frame. Streamed to the file one frame at a time (a
/// long turntable need not fit in memory), atomic like every writer here.
pub fn write_apng(path: &Path, frames: &[PathBuf], fps: u16) -> Result<()> {
    let Some(first) = frames.first() else {
        return Err(Error::invalid(path.display().to_string(), "an animation needs at least one frame"));
    };
    if fps == 0 {
        return Err(Error::invalid(path.display().to_string(), "frame rate 0"));
    }
    let count =
        u32::try_from(frames.len()).map_err(|_| Error::invalid(path.display().to_string(), "too many frames"))?;
    // Sizes from the headers first, so that a wrong frame is named before anything is written.
    let (width, height) = image_dimensions(first)?;
    for frame in &frames[1..] {
        let (w, h) = image_dimensions(frame)?;
        if (w, h) != (width, height) {
            return Err(Error::invalid(
                frame.display().to_string(),
                format!("is {w} × {h}, the animation's first frame {width} × {height}"),
            ));
        }
    }
    let other = |e: &dyn std::fmt::Display| std::io::Error::other(e.to_string());
    crate::io::atomic::write_atomic_with(path, |out| {
        let mut encoder = png::Encoder::new(out, width, height);
        encoder.set_color(png::ColorType::Rgba);
        encoder.set_depth(png::BitDepth::Eight);
        encoder.set_compression(png::Compression::Fast);
        encoder.set_filter(png::Filter::Adaptive);
        encoder.set_animated(count, 0).map_err(|e| other(&e))?;
        encoder.set_frame_delay(1, fps).map_err(|e| other(&e))?;
        let mut writer = encoder.write_header().map_err(|e| other(&e))?;
        for frame in frames {
            let img = read_rgba(frame).map_err(|e| other(&e))?;
            // read_rgba gives k / 255 for 8-bit samples; this rounds back to k exactly.
            let pixels: Vec<u8> = img.data.iter().map(|&v| (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8).collect();
            writer.write_image_data(&pixels).map_err(|e| other(&e))?;
        }
        writer.finish().map_err(|e| other(&e))
    })
}

/// OpenEXR, ZIP-compressed scan lines in increasing order. The exr default (tiles in
/// unspecified order, compressed in parallel) could give the same picture as different bytes
/// from run to run; a run's outputs must be reproducible.
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
    let bytes = match format_of(path) {
        Some(Format::Png) => encode_png(img, path)?,
        Some(Format::Exr) => encode_exr(img, path)?,
        Some(Format::Hdr) => rgbe::encode(path, &expand_to(img, 3))?,
        None => {
            return Err(Error::invalid(path.display().to_string(), "unknown image extension (use png, exr or hdr)"));
        }
    };
    write_atomic(path, &bytes)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_dir::TempDir;

    /// Distance in ulps between two positive finite f32.
    fn ulps(a: f32, b: f32) -> u32 {
        a.to_bits().abs_diff(b.to_bits())
    }

    /// The table-and-polynomial power is within an ulp of the correctly rounded t^2.4 over
    /// every octave it covers (and the f64 power, a reference independent of it), and falls
    /// back to powf outside them.
    #[test]
    fn pow_2_4_is_within_an_ulp() {
        let mut worst = 0;
        let mut t = 2f32.powi(-4);
        while t < 512.0 {
            let exact = (t as f64).powf(2.4) as f32;
            worst = worst.max(ulps(pow_2_4(t), exact));
            // Every mantissa region: octave edges, odd mantissas, values near m = 2.
            t = f32::from_bits(t.to_bits() + 997);
        }
        assert!(worst <= 1, "worst {worst} ulp");
        for t in [2f32.powi(-4), 1.0, 1.0f32.next_down(), 2.0, 512.0f32.next_down()] {
            assert!(ulps(pow_2_4(t), (t as f64).powf(2.4) as f32) <= 1, "t {t}");
        }
        for t in [0.0f32, 1e-3, 0.0624, 512.0, 1e6, f32::MAX, f32::INFINITY] {
            assert_eq!(pow_2_4(t).to_bits(), t.powf(2.4).to_bits(), "t {t}");
        }
        assert!(pow_2_4(f32::NAN).is_nan());
        assert!(pow_2_4(-1.0).is_nan());
        // The sRGB decode over its power segment, to an ulp of the exact power of its f32 base.
        for k in 0..=10_000 {
            let x = 0.040_46 + 2.0 * k as f32 / 10_000.0;
            let t = (x + 0.055) / 1.055;
            assert!(ulps(srgb_to_linear(x), (t as f64).powf(2.4) as f32) <= 1, "x {x}");
        }
    }

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
        let dir = TempDir::new("img");
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
            let dir = TempDir::new(&format!("exr-{channels}"));
            write_image(&dir.join("a.exr"), &img).unwrap();
            let back = read_rgba(&dir.join("a.exr")).unwrap();
            assert_eq!(back, expand_to(&img, 4));
        }
    }

    #[test]
    fn an_animation_refuses_frames_of_another_size_by_name() {
        let dir = TempDir::new("apng");
        let (a, b) = (dir.join("a.png"), dir.join("b.png"));
        write_image(&a, &Image::new(4, 3, 4)).unwrap();
        write_image(&b, &Image::new(3, 4, 4)).unwrap();
        let out = dir.join("anim.apng");
        write_apng(&out, &[a.clone(), a.clone()], 24).unwrap();
        assert_eq!(image_dimensions(&out).unwrap(), (4, 3));
        let err = write_apng(&dir.join("bad.apng"), &[a.clone(), b], 24).unwrap_err().to_string();
        assert!(err.contains("b.png") && err.contains("3 × 4"), "{err}");
        assert!(!dir.join("bad.apng").exists());
        assert!(write_apng(&out, &[], 24).is_err() && write_apng(&out, &[a], 0).is_err());
    }

    /// Other formats (JPEG here) are refused by name, nothing written.
    #[test]
    fn unsupported_output_format_is_refused() {
        let dir = TempDir::new("fmt");
        let path = dir.join("a.jpg");
        let err = write_image(&path, &Image::new(4, 4, 3)).unwrap_err().to_string();
        assert!(err.contains("a.jpg") && err.contains("png, exr or hdr"), "{err}");
        assert!(!path.exists());
    }

    #[test]
    fn truncated_png_names_the_file() {
        let dir = TempDir::new("trunc");
        let img = Image::new(16, 16, 4);
        let path = dir.join("view.png");
        write_image(&path, &img).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        std::fs::write(&path, &bytes[..bytes.len() / 2]).unwrap();
        let err = read_rgba(&path).unwrap_err().to_string();
        assert!(err.contains("view.png") && err.contains("ends early"), "{err}");
        // Every cut into the header or pixels, down to an empty file, fails (never panics)
        // naming the file, also when only checked or only the size is read. (A file cut in its
        // 12-byte end chunk still holds every pixel, and reads.)
        for len in 0..bytes.len() - 12 {
            std::fs::write(&path, &bytes[..len]).unwrap();
            for err in [read_rgba(&path).unwrap_err(), check_image(&path).unwrap_err()] {
                let err = err.to_string();
                assert!(err.contains("view.png") && err.contains("ends early"), "{len}: {err}");
            }
            if len < 33 {
                let err = image_dimensions(&path).unwrap_err().to_string();
                assert!(err.contains("view.png") && err.contains("ends early"), "{len}: {err}");
            }
        }
    }

    /// A PNG built with the png encoder: any colour type and depth, optional palette and tRNS,
    /// and gAMA + sRGB chunks that the reader must not apply.
    fn png_file(w: u32, colour: png::ColorType, depth: png::BitDepth, extra: (&[u8], &[u8]), rows: &[u8]) -> Vec<u8> {
        let (palette, trns) = extra;
        let mut bytes = Vec::new();
        let row_len = (w as usize * colour.samples() * depth as usize).div_ceil(8);
        let mut enc = png::Encoder::new(&mut bytes, w, (rows.len() / row_len) as u32);
        enc.set_color(colour);
        enc.set_depth(depth);
        enc.set_source_gamma(png::ScaledFloat::new(0.3));
        enc.set_source_srgb(png::SrgbRenderingIntent::Perceptual);
        if !palette.is_empty() {
            enc.set_palette(palette.to_vec());
        }
        if !trns.is_empty() {
            enc.set_trns(trns.to_vec());
        }
        let mut writer = enc.write_header().unwrap();
        writer.write_image_data(rows).unwrap();
        writer.finish().unwrap();
        bytes
    }

    #[test]
    fn png_colour_types_and_depths_read_as_stored() {
        use png::BitDepth::{Eight, Four, Sixteen, Two};
        use png::ColorType::{Grayscale, GrayscaleAlpha, Indexed, Rgb, Rgba};
        let (o, t) = (1.0, 1.0 / 3.0);
        let b = |v: f32| v / 255.0;
        let w = |v: f32| v / 65535.0;
        let cases: Vec<(Vec<u8>, Vec<[f32; 4]>)> = vec![
            (
                png_file(3, Grayscale, Eight, (&[], &[]), &[0, 51, 255]),
                vec![[0.0, 0.0, 0.0, o], [0.2, 0.2, 0.2, o], [o; 4]],
            ),
            (
                png_file(2, Grayscale, Sixteen, (&[], &[]), &[0x80, 0, 0xff, 0xff]),
                vec![[w(32768.0), w(32768.0), w(32768.0), o], [o; 4]],
            ),
            // Two bits a sample, scaled to the full range.
            (
                png_file(4, Grayscale, Two, (&[], &[]), &[0b00_01_10_11]),
                vec![[0.0, 0.0, 0.0, o], [t, t, t, o], [2.0 * t, 2.0 * t, 2.0 * t, o], [o; 4]],
            ),
            // tRNS on grey: that one value becomes transparent.
            (
                png_file(2, Grayscale, Eight, (&[], &[0, 51]), &[51, 52]),
                vec![[0.2, 0.2, 0.2, 0.0], [b(52.0), b(52.0), b(52.0), o]],
            ),
            (png_file(1, GrayscaleAlpha, Eight, (&[], &[]), &[10, 20]), vec![[b(10.0), b(10.0), b(10.0), b(20.0)]]),
            (
                png_file(1, GrayscaleAlpha, Sixteen, (&[], &[]), &[0, 10, 0xff, 0xff]),
                vec![[w(10.0), w(10.0), w(10.0), o]],
            ),
            (
                png_file(2, Rgb, Eight, (&[], &[0, 1, 0, 2, 0, 3]), &[1, 2, 3, 4, 5, 6]),
                vec![[b(1.0), b(2.0), b(3.0), 0.0], [b(4.0), b(5.0), b(6.0), o]],
            ),
            (png_file(1, Rgb, Sixteen, (&[], &[]), &[0, 1, 1, 0, 0xff, 0xff]), vec![[w(1.0), w(256.0), o, o]]),
            (png_file(1, Rgba, Eight, (&[], &[]), &[255, 0, 51, 102]), vec![[o, 0.0, 0.2, 0.4]]),
            (
                png_file(1, Rgba, Sixteen, (&[], &[]), &[0, 0, 0, 2, 0x80, 0, 0xff, 0xfe]),
                vec![[0.0, w(2.0), w(32768.0), w(65534.0)]],
            ),
            // Palette, 4 bits an index, tRNS for the first entry only: indices 0, 1, 2 (+ padding).
            (
                png_file(3, Indexed, Four, (&[255, 0, 0, 0, 255, 0, 0, 0, 51], &[128]), &[0x01, 0x20]),
                vec![[o, 0.0, 0.0, b(128.0)], [0.0, o, 0.0, o], [0.0, 0.0, 0.2, o]],
            ),
        ];
        let dir = TempDir::new("pngtypes");
        let path = dir.join("p.png");
        for (i, (bytes, expect)) in cases.iter().enumerate() {
            std::fs::write(&path, bytes).unwrap();
            let img = read_rgba(&path).unwrap();
            assert_eq!((img.width as usize, img.height), (expect.len(), 1), "case {i}");
            for (got, want) in img.data.chunks_exact(4).zip(expect) {
                for k in 0..4 {
                    assert!((got[k] - want[k]).abs() < 1e-6, "case {i}: {got:?} vs {want:?}");
                }
            }
            assert_eq!(check_image(&path).unwrap(), (img.width, 1));
            assert_eq!(image_dimensions(&path).unwrap(), (img.width, 1));
        }
    }

    /// A palette index past the palette's end is refused by name (the decoder's expansion would
    /// read it as black); every depth's packing is unpacked, padding bits are not indices.
    #[test]
    fn palette_indices_past_the_palette_are_refused() {
        use png::BitDepth::{Eight, Four, One};
        use png::ColorType::Indexed;
        let dir = TempDir::new("pngpalette");
        let path = dir.join("p.png");
        let two = [255, 0, 0, 0, 255, 0];
        let cases: [(Vec<u8>, Option<&str>); 5] = [
            // 4 bits: indices 0, 1, 5 (+ a padding nibble of 15, not an index).
            (png_file(3, Indexed, Four, (&two, &[]), &[0x01, 0x5f]), Some("pixel (2, 0) has palette index 5")),
            (png_file(3, Indexed, Four, (&two, &[]), &[0x01, 0x1f]), None),
            (png_file(2, Indexed, Eight, (&two, &[]), &[1, 200]), Some("pixel (1, 0) has palette index 200")),
            // 1 bit, one colour: the third pixel's bit is set.
            (png_file(4, Indexed, One, (&two[..3], &[]), &[0b0010_1111]), Some("pixel (2, 0) has palette index 1")),
            (png_file(4, Indexed, One, (&two[..3], &[]), &[0b0000_1111]), None),
        ];
        for (i, (bytes, refused)) in cases.iter().enumerate() {
            std::fs::write(&path, bytes).unwrap();
            match refused {
                Some(says) => {
                    for err in [read_rgba(&path).unwrap_err(), check_image(&path).unwrap_err()] {
                        let err = err.to_string();
                        assert!(
                            err.contains("p.png") && err.contains(says) && err.contains("palette has"),
                            "{i}: {err}"
                        );
                    }
                }
                None => {
                    read_rgba(&path).unwrap();
                }
            }
        }
    }

    #[test]
    fn png_bytes_are_reproducible_and_read_back() {
        let path = Path::new("a.png");
        for channels in 1..=4 {
            let mut img = Image::new(37, 9, channels);
            for (i, v) in img.data.iter_mut().enumerate() {
                *v = ((i * 7919) % 301) as f32 / 255.0 - 0.1;
            }
            let first = encode_png(&img, path).unwrap();
            assert!(encode_png(&img, path).unwrap() == first);
            let dir = TempDir::new(&format!("pngrt-{channels}"));
            write_image(&dir.join("a.png"), &img).unwrap();
            let back = read_rgba(&dir.join("a.png")).unwrap();
            let expect = expand_to(&img, 4);
            // Each value comes back as its nearest 8-bit level (grey within a rounding of it).
            for (a, b) in expect.data.iter().zip(&back.data) {
                let level = (a.clamp(0.0, 1.0) * 255.0 + 0.5).floor() / 255.0;
                assert!((b - level).abs() < 1e-7, "{a} → {b}");
            }
        }
    }

    #[test]
    fn corrupt_and_oversized_pngs_are_refused_by_name() {
        let dir = TempDir::new("pngbad");
        let path = dir.join("bad.png");
        let mut img = Image::new(9, 5, 4);
        img.data.iter_mut().enumerate().for_each(|(i, v)| *v = (i % 7) as f32 / 6.0);
        let good = encode_png(&img, &path).unwrap();
        // Any byte changed gives an image or an error naming the file, never a panic.
        for i in 0..good.len() {
            for v in [0u8, 0x7f, 0xff] {
                let mut bytes = good.clone();
                bytes[i] = v;
                std::fs::write(&path, &bytes).unwrap();
                if let Err(e) = read_rgba(&path) {
                    assert!(e.to_string().contains("bad.png"), "{e}");
                }
            }
        }
        // Headers promising too many pixels, or more than the file could hold: refused before
        // any buffer is made (the signature and IHDR alone, as the encoder writes them).
        let header = |w: u32, h: u32| {
            let mut bytes = Vec::new();
            let mut enc = png::Encoder::new(&mut bytes, w, h);
            enc.set_color(png::ColorType::Rgba);
            std::mem::forget(enc.write_header().unwrap());
            bytes[..33].to_vec()
        };
        for (w, h, expect) in [(20000, 20000, "more than the"), (10000, 10000, "cannot fit in 33 bytes")] {
            std::fs::write(&path, header(w, h)).unwrap();
            let err = read_rgba(&path).unwrap_err().to_string();
            assert!(err.contains("bad.png") && err.contains(expect), "{err}");
            // The size alone is read from the header.
            assert_eq!(image_dimensions(&path).unwrap(), (w, h));
        }
    }

    #[test]
    fn an_exr_header_promising_too_many_pixels_is_refused_before_decoding() {
        // A scan-line header alone (no offset table, no pixels) whose data window claims
        // 200000 × 100000 pixels: the decoder would allocate 80 GB for it.
        fn attr(name: &str, kind: &str, data: &[u8]) -> Vec<u8> {
            let mut v = [name.as_bytes(), &[0], kind.as_bytes(), &[0]].concat();
            v.extend((data.len() as i32).to_le_bytes());
            v.extend(data);
            v
        }
        let mut channels = Vec::new();
        for c in ["A", "B", "G", "R"] {
            channels.extend([c.as_bytes(), &[0]].concat());
            channels.extend(2i32.to_le_bytes()); // f32 samples
            channels.extend([0u8; 4]);
            channels.extend(1i32.to_le_bytes());
            channels.extend(1i32.to_le_bytes());
        }
        channels.push(0);
        let window: Vec<u8> = [0i32, 0, 199_999, 99_999].iter().flat_map(|v| v.to_le_bytes()).collect();
        let mut bytes = vec![0x76, 0x2f, 0x31, 0x01];
        bytes.extend(2i32.to_le_bytes());
        for a in [
            attr("channels", "chlist", &channels),
            attr("compression", "compression", &[0]),
            attr("dataWindow", "box2i", &window),
            attr("displayWindow", "box2i", &window),
            attr("lineOrder", "lineOrder", &[0]),
            attr("pixelAspectRatio", "float", &1f32.to_le_bytes()),
            attr("screenWindowCenter", "v2f", &[0u8; 8]),
            attr("screenWindowWidth", "float", &1f32.to_le_bytes()),
        ] {
            bytes.extend(a);
        }
        bytes.push(0);
        let dir = TempDir::new("exrhuge");
        let path = dir.join("huge.exr");
        std::fs::write(&path, &bytes).unwrap();
        assert_eq!(image_dimensions(&path).unwrap(), (200_000, 100_000));
        let err = read_rgba(&path).unwrap_err().to_string();
        assert!(err.contains("huge.exr") && err.contains("more than the"), "{err}");
    }

    #[test]
    fn formats_follow_the_extension() {
        let dir = TempDir::new("ext");
        let mut img = Image::new(12, 6, 3);
        img.data.iter_mut().enumerate().for_each(|(i, v)| *v = i as f32 * 0.75);
        for name in ["a.HDR", "b.hdr", "c.exr", "d.Png"] {
            write_image(&dir.join(name), &img).unwrap();
            assert_eq!(image_dimensions(&dir.join(name)).unwrap(), (12, 6), "{name}");
            assert_eq!(read_rgba(&dir.join(name)).unwrap().width, 12);
        }
        // The .hdr holds the RGBE-quantised values (within 1/128 of the largest component).
        let back = read_rgba(&dir.join("b.hdr")).unwrap();
        for (a, b) in expand_to(&img, 4).data.chunks_exact(4).zip(back.data.chunks_exact(4)) {
            assert!(a.iter().zip(b).all(|(x, y)| (x - y).abs() <= a[2].max(1.0) / 128.0), "{a:?} {b:?}");
        }
        std::fs::write(dir.join("e.jpg"), b"not read").unwrap();
        let err = read_rgba(&dir.join("e.jpg")).unwrap_err().to_string();
        assert!(err.contains("e.jpg") && err.contains("not a known image type"), "{err}");
        let err = image_dimensions(&dir.join("e.jpg")).unwrap_err().to_string();
        assert!(err.contains("e.jpg") && err.contains("not a known image type"), "{err}");
        std::fs::write(dir.join("f.hdr"), b"").unwrap();
        let err = image_dimensions(&dir.join("f.hdr")).unwrap_err().to_string();
        assert!(err.contains("f.hdr") && err.contains("ends early"), "{err}");
    }
}

//! Radiance RGBE (.hdr) files, read and written by hand: three 8-bit mantissas sharing one 8-bit
//! exponent per pixel, scanlines top to bottom, each flat, old-style run-length encoded or
//! new-style (per component) run-length encoded.
//!
//! The float ↔ RGBE conversions and the writer's run choices are those of the `image` crate
//! (0.25), which this replaces, so the same floats give the same bytes and the same bytes the same
//! floats: a synthetic scene lit by a map read back from its .hdr is lit exactly as before.
//! Where that crate's output was broken this one differs: a width of 32768 is written flat (its
//! run-length marker would not fit), maxima below 2⁻¹²⁷ are written as 0 and at or above 2¹²⁷
//! saturate (instead of wrapping the exponent byte), and NaN or infinity is refused.

use crate::error::{Error, Result};
use crate::io::image::{Image, MAX_PIXELS, TRUNCATED};
use std::path::Path;

/// Scanlines of these widths carry the new-style run-length marker (the marker's width field
/// has 15 bits; narrower lines gain nothing from it).
const RLE_WIDTHS: std::ops::RangeInclusive<usize> = 8..=0x7fff;

/// The header the writer emits before the resolution line (as the `image` crate's writer did,
/// so files stay byte-identical).
const HEADER: &[u8] = b"#?RADIANCE\n# Rust HDR encoder\nFORMAT=32-bit_rle_rgbe\n\n";

/// A run of equal bytes longer than this is split (the count byte is 128 + length).
const MAX_RUN: usize = 127;
/// A literal stretch longer than this is split (the count byte is its length).
const MAX_LITERAL: usize = 128;

/// RGBE → linear RGB: component × 2^(e − 136); e = 0 is black.
pub fn rgbe_to_rgb(p: [u8; 4]) -> [f32; 3] {
    let e = p[3] as u32;
    // 2^(e − 128) built from its bits; e = 1 needs the subnormal 2⁻¹²⁷, e = 0 gives 0.
    let scale = f32::from_bits(if e > 1 { (e - 1) << 23 } else { e << 22 }) * 0.003_906_25;
    [scale * p[0] as f32, scale * p[1] as f32, scale * p[2] as f32]
}

/// Linear RGB (finite) → RGBE: the largest component's binary exponent is shared, mantissas are
/// truncated; a pixel whose largest component is ≤ 0 (or below 2⁻¹²⁷) is black.
pub fn rgb_to_rgbe(rgb: [f32; 3]) -> [u8; 4] {
    let max = rgb[0].max(rgb[1].max(rgb[2]));
    if max <= 0.0 {
        return [0; 4];
    }
    let exp = (max.log2().floor() as i32 + 1).min(127);
    if exp < -127 {
        return [0; 4];
    }
    // 2^exp is exact over −127..=127, so powi's rounding cannot differ from the old writer's.
    let scale = 2f32.powi(exp);
    let mantissa = |v: f32| (v / scale * 256.0).trunc() as u8;
    [mantissa(rgb[0]), mantissa(rgb[1]), mantissa(rgb[2]), (exp + 128) as u8]
}

/// Decode a whole .hdr file held in `bytes` to a 3-channel linear image.
pub fn decode(path: &Path, bytes: &[u8]) -> Result<Image> {
    let mut r = Reader { path, bytes, pos: 0 };
    let (width, height) = read_header(&mut r)?;
    if width == 0 || height == 0 {
        return Ok(Image { width, height, channels: 3, data: Vec::new() });
    }
    // The whole image at once when the rest of the file could hold it (new-style runs take at
    // least 8 bytes per 127 pixels; old-style runs, which can take less, grow the buffer), so a
    // header alone cannot make a huge buffer.
    let pixels = (width as usize * height as usize).min((bytes.len() - r.pos).saturating_mul(16));
    let mut data = Vec::with_capacity(pixels * 3);
    let mut line = Vec::new();
    for y in 0..height {
        read_scanline(&mut r, y, width as usize, &mut line)?;
        data.extend(line.iter().flat_map(|&p| rgbe_to_rgb(p)));
    }
    Ok(Image { width, height, channels: 3, data })
}

/// The width and height from a .hdr file's header, without reading its pixels.
pub fn dimensions(path: &Path, bytes: &[u8]) -> Result<(u32, u32)> {
    read_header(&mut Reader { path, bytes, pos: 0 })
}

/// Encode a 3-channel image as .hdr: new-style run-length scanlines when the width allows it,
/// flat pixels otherwise.
pub fn encode(path: &Path, img: &Image) -> Result<Vec<u8>> {
    let (w, h) = (img.width as usize, img.height as usize);
    if img.channels != 3 || img.data.len() != w * h * 3 {
        return Err(Error::invalid(path.display().to_string(), "image buffer has the wrong size"));
    }
    if let Some(bad) = img.data.iter().position(|v| !v.is_finite()) {
        let px = bad / 3;
        return Err(Error::invalid(
            path.display().to_string(),
            format!("pixel ({}, {}): value is NaN or infinite, which RGBE cannot store", px % w, px / w),
        ));
    }
    let pixels: Vec<[u8; 4]> = img.data.chunks_exact(3).map(|p| rgb_to_rgbe([p[0], p[1], p[2]])).collect();
    let mut out = Vec::with_capacity(HEADER.len() + 32 + pixels.len() * 4);
    out.extend_from_slice(HEADER);
    out.extend_from_slice(format!("-Y {h} +X {w}\n").as_bytes());
    if !RLE_WIDTHS.contains(&w) {
        out.extend(pixels.iter().flatten());
        return Ok(out);
    }
    let mut component = vec![0u8; w];
    for row in pixels.chunks_exact(w) {
        out.extend_from_slice(&[2, 2, (w >> 8) as u8, (w & 0xff) as u8]);
        for c in 0..4 {
            component.iter_mut().zip(row).for_each(|(dst, p)| *dst = p[c]);
            compress_component(&component, &mut out);
        }
    }
    Ok(out)
}

/// Runs of three or more equal bytes (up to [`MAX_RUN`]) become (128 + n, byte); everything
/// between runs is written as literal stretches of up to [`MAX_LITERAL`] bytes.
fn compress_component(data: &[u8], out: &mut Vec<u8>) {
    let (mut literal_start, mut i) = (0, 0);
    while i < data.len() {
        let run = data[i..].iter().take(MAX_RUN).take_while(|&&v| v == data[i]).count();
        if run > 2 {
            push_literals(&data[literal_start..i], out);
            out.extend_from_slice(&[128 + run as u8, data[i]]);
            literal_start = i + run;
        }
        i += run;
    }
    push_literals(&data[literal_start..], out);
}

fn push_literals(literals: &[u8], out: &mut Vec<u8>) {
    for chunk in literals.chunks(MAX_LITERAL) {
        out.push(chunk.len() as u8);
        out.extend_from_slice(chunk);
    }
}

/// The bytes of the file and how far they have been read; errors name the file.
struct Reader<'a> {
    path: &'a Path,
    bytes: &'a [u8],
    pos: usize,
}

impl<'a> Reader<'a> {
    /// The next line without its '\n', or None if the file ends first (a header line cut short
    /// is a truncated file, not a line to misread).
    fn line(&mut self) -> Option<&'a [u8]> {
        let rest = &self.bytes[self.pos.min(self.bytes.len())..];
        let len = rest.iter().position(|&b| b == b'\n')?;
        self.pos += len + 1;
        Some(&rest[..len])
    }
    fn take(&mut self, n: usize, field: impl Fn() -> String) -> Result<&'a [u8]> {
        let end = self.pos.checked_add(n).filter(|&end| end <= self.bytes.len());
        let end = end.ok_or_else(|| Error::format(self.path, field(), TRUNCATED))?;
        let out = &self.bytes[self.pos..end];
        self.pos = end;
        Ok(out)
    }
    fn byte(&mut self, field: impl Fn() -> String) -> Result<u8> {
        Ok(self.take(1, field)?[0])
    }
    fn pixel(&mut self, field: impl Fn() -> String) -> Result<[u8; 4]> {
        let p = self.take(4, field)?;
        Ok([p[0], p[1], p[2], p[3]])
    }
    fn error(&self, field: impl Into<String>, reason: impl Into<String>) -> Error {
        Error::format(self.path, field, reason)
    }
}

/// Signature, header lines up to the blank line, then the resolution line: (width, height).
fn read_header(r: &mut Reader) -> Result<(u32, u32)> {
    let truncated = |r: &Reader, field: &str| r.error(field, TRUNCATED);
    let signature = r.line().ok_or_else(|| truncated(r, "header"))?;
    if !(signature.starts_with(b"#?RADIANCE") || signature.starts_with(b"#?RGBE")) {
        return Err(r.error("header", "no #?RADIANCE or #?RGBE signature (not a Radiance .hdr file)"));
    }
    loop {
        let line = r.line().ok_or_else(|| truncated(r, "header"))?;
        if line.is_empty() {
            break;
        }
        if line[0] == b'#' {
            continue;
        }
        let line = String::from_utf8_lossy(line);
        if let Some((key, value)) = line.split_once('=')
            && key.trim() == "FORMAT"
            && value.trim() != "32-bit_rle_rgbe"
        {
            return Err(r.error(
                "FORMAT",
                format!("{} is not supported (only 32-bit_rle_rgbe, not XYZE)", shorten(value.trim())),
            ));
        }
    }
    let line = r.line().ok_or_else(|| truncated(r, "resolution line"))?;
    let (width, height) = parse_resolution(r, &String::from_utf8_lossy(line))?;
    if width as u64 * height as u64 > MAX_PIXELS {
        return Err(r.error(
            "resolution line",
            format!("{width}×{height} is more than the {MAX_PIXELS} pixels an image may have"),
        ));
    }
    Ok((width, height))
}

/// "-Y <height> +X <width>": rows from the top, pixels from the left (the only orientation
/// read; the seven others would need the image flipped or transposed).
fn parse_resolution(r: &Reader, line: &str) -> Result<(u32, u32)> {
    let field = "resolution line";
    let parts: Vec<&str> = line.split_ascii_whitespace().collect();
    let [axis1, size1, axis2, size2] = parts[..] else {
        return Err(r.error(field, format!("{:?} is not of the form -Y <height> +X <width>", shorten(line))));
    };
    if (axis1, axis2) != ("-Y", "+X") {
        return Err(r.error(
            field,
            format!("orientation {} {} is not supported (only -Y <height> +X <width>)", shorten(axis1), shorten(axis2)),
        ));
    }
    let size = |s: &str, what: &str| {
        s.parse::<u32>().map_err(|_| r.error(field, format!("{what} {:?} is not a whole number", shorten(s))))
    };
    Ok((size(size2, "width")?, size(size1, "height")?))
}

/// At most 20 characters of `s` for a message (a binary file's "line" can be anything).
fn shorten(s: &str) -> String {
    if s.chars().count() > 20 { s.chars().take(20).chain("…".chars()).collect() } else { s.to_string() }
}

/// Decode scanline `y` into `line` (cleared first): new-style if it starts with the marker,
/// else flat / old-style run-length.
fn read_scanline(r: &mut Reader, y: u32, width: usize, line: &mut Vec<[u8; 4]>) -> Result<()> {
    line.clear();
    if width == 0 {
        return Ok(());
    }
    let field = || format!("scanline {y}");
    let first = r.pixel(field)?;
    if RLE_WIDTHS.contains(&width) && first[0] == 2 && first[1] == 2 && first[2] < 128 {
        let marked = (first[2] as usize) << 8 | first[3] as usize;
        if marked != width {
            return Err(r.error(field(), format!("its run-length marker says {marked} pixels, the header {width}")));
        }
        // The width is below 2¹⁵ here, so this buffer is small whatever the header claims.
        line.resize(width, [0; 4]);
        for c in 0..4 {
            read_component(r, &field, line, c)?;
        }
        Ok(())
    } else {
        read_old_scanline(r, &field, first, width, line)
    }
}

/// One component of a new-style scanline: count bytes > 128 repeat the next byte count − 128
/// times, others are followed by that many literal bytes.
fn read_component(r: &mut Reader, field: &dyn Fn() -> String, line: &mut [[u8; 4]], c: usize) -> Result<()> {
    let mut x = 0;
    while x < line.len() {
        let code = r.byte(field)? as usize;
        let n = if code > 128 { code - 128 } else { code };
        if x + n > line.len() {
            return Err(r.error(field(), format!("a run reaches pixel {} of {}", x + n, line.len())));
        }
        if code > 128 {
            let v = r.byte(field)?;
            line[x..x + n].iter_mut().for_each(|p| p[c] = v);
        } else {
            let values = r.take(n, field)?;
            line[x..x + n].iter_mut().zip(values).for_each(|(p, &v)| p[c] = v);
        }
        x += n;
    }
    Ok(())
}

/// Flat pixels, where (1, 1, 1, n) repeats the previous pixel n times (n × 256 for each
/// further marker in a row, Radiance's old-style run-length encoding).
fn read_old_scanline(
    r: &mut Reader,
    field: &dyn Fn() -> String,
    first: [u8; 4],
    width: usize,
    line: &mut Vec<[u8; 4]>,
) -> Result<()> {
    let is_run = |p: [u8; 4]| p[..3] == [1, 1, 1];
    if is_run(first) {
        return Err(r.error(field(), "starts with a run-length marker (nothing to repeat)"));
    }
    line.push(first);
    let (mut previous, mut multiplier) = (first, 1u64);
    while line.len() < width {
        let p = r.pixel(field)?;
        if !is_run(p) {
            line.push(p);
            previous = p;
            multiplier = 1;
            continue;
        }
        let n = (p[3] as u64).saturating_mul(multiplier);
        let end = (line.len() as u64).saturating_add(n);
        if end > width as u64 {
            return Err(r.error(field(), format!("a run reaches pixel {end} of {width}")));
        }
        line.resize(line.len() + n as usize, previous);
        multiplier = multiplier.saturating_mul(256);
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn header(w: u32, h: u32) -> Vec<u8> {
        format!("#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y {h} +X {w}\n").into_bytes()
    }

    fn err_of(bytes: &[u8]) -> String {
        decode(Path::new("sky.hdr"), bytes).unwrap_err().to_string()
    }

    #[test]
    fn rgbe_conversions_match_the_format() {
        assert_eq!(rgbe_to_rgb([128, 64, 0, 129]), [1.0, 0.5, 0.0]);
        assert_eq!(rgbe_to_rgb([200, 1, 7, 0]), [0.0; 3]);
        // e = 1: the subnormal 2⁻¹²⁷ scale.
        assert_eq!(rgbe_to_rgb([128, 0, 0, 1]), [2f32.powi(-128), 0.0, 0.0]);
        assert_eq!(rgb_to_rgbe([1.0, 0.5, 0.0]), [128, 64, 0, 129]);
        assert_eq!(rgb_to_rgbe([0.0, -3.0, 0.0]), [0; 4]);
        assert_eq!(rgb_to_rgbe([1e-39, 0.0, 0.0]), [0; 4]);
        assert_eq!(rgb_to_rgbe([f32::MAX, 0.0, 1.0]), [255, 0, 0, 255]);
        // Every RGBE with a normalised mantissa survives the round trip.
        for e in 1..=255u8 {
            for m in [128u8, 129, 200, 255] {
                let p = [m, m / 2, 0, e];
                assert_eq!(rgb_to_rgbe(rgbe_to_rgb(p)), p, "{p:?}");
            }
        }
    }

    #[test]
    fn flat_file_built_by_hand() {
        let mut bytes = b"#?RGBE\n# made by hand\nEXPOSURE=2\n\n-Y 2 +X 3\n".to_vec();
        let pixels =
            [[128, 0, 0, 129], [0, 128, 0, 130], [0, 0, 0, 0], [64, 64, 64, 128], [255, 0, 1, 136], [1, 2, 3, 120]];
        pixels.iter().for_each(|p| bytes.extend(p));
        let img = decode(Path::new("a.hdr"), &bytes).unwrap();
        assert_eq!((img.width, img.height, img.channels), (3, 2, 3));
        let expect: Vec<f32> = pixels.iter().flat_map(|&p| rgbe_to_rgb(p)).collect();
        assert_eq!(img.data, expect);
        assert_eq!(img.data[..9], [1.0, 0.0, 0.0, 0.0, 2.0, 0.0, 0.0, 0.0, 0.0]);
        // EXPOSURE is recorded, not applied (as Radiance readers leave it to the caller).
        assert_eq!(img.data[9], 0.25);
        assert_eq!(dimensions(Path::new("a.hdr"), &bytes).unwrap(), (3, 2));
    }

    #[test]
    fn new_style_rle_file_built_by_hand() {
        // Width 10: R is a run of 10 × 128; G is 5 literals then a run of 5 × 7; B all 0 as
        // two runs; E is literals.
        let mut bytes = header(10, 1);
        bytes.extend([2, 2, 0, 10]);
        bytes.extend([128 + 10, 128]);
        bytes.extend([5, 1, 2, 3, 4, 5, 128 + 5, 7]);
        bytes.extend([128 + 4, 0, 128 + 6, 0]);
        bytes.extend([10, 129, 129, 129, 130, 130, 130, 131, 131, 131, 0]);
        let img = decode(Path::new("a.hdr"), &bytes).unwrap();
        let e = [129, 129, 129, 130, 130, 130, 131, 131, 131, 0];
        let g = [1, 2, 3, 4, 5, 7, 7, 7, 7, 7];
        let expect: Vec<f32> = (0..10).flat_map(|x| rgbe_to_rgb([128, g[x], 0, e[x]])).collect();
        assert_eq!(img.data, expect);
        assert_eq!(img.data[..3], [1.0, 1.0 / 128.0, 0.0]);
    }

    #[test]
    fn old_style_runs_repeat_the_previous_pixel() {
        // Width 300 (new-style allowed, but this line does not start with the marker): one
        // pixel, then runs of 43 and 1 × 256 (a second marker in a row counts 256-fold).
        let mut bytes = header(300, 1);
        bytes.extend([10, 20, 30, 130]);
        bytes.extend([1, 1, 1, 43]);
        bytes.extend([1, 1, 1, 1]);
        let img = decode(Path::new("a.hdr"), &bytes).unwrap();
        assert_eq!(img.data.len(), 900);
        assert!(img.data.chunks_exact(3).all(|p| p == rgbe_to_rgb([10, 20, 30, 130])));
        // A run past the end of the line, or with nothing to repeat, is an error.
        let mut long = header(8, 1);
        long.extend([10, 20, 30, 130, 1, 1, 1, 8]);
        assert!(err_of(&long).contains("scanline 0"), "{}", err_of(&long));
        let mut first = header(8, 1);
        first.extend([1, 1, 1, 7]);
        assert!(err_of(&first).contains("nothing to repeat"), "{}", err_of(&first));
        // Many markers in a row cannot overflow the multiplier.
        let mut chain = header(4, 1);
        chain.extend([9, 9, 9, 140]);
        (0..20).for_each(|_| chain.extend([1, 1, 1, 0]));
        chain.extend([1, 1, 1, 3]);
        assert!(err_of(&chain).contains("a run reaches"), "{}", err_of(&chain));
    }

    fn test_image(width: u32, height: u32, seed: u64) -> Image {
        let mut img = Image::new(width, height, 3);
        let mut state = seed;
        for v in &mut img.data {
            state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            let u = (state >> 40) as f32 / (1u64 << 24) as f32;
            // Runs of repeats (flat areas) and values from 1e-30 to 1e5, zeros, powers of two.
            *v = match (state >> 20) % 8 {
                0 => 0.0,
                1 => 2f32.powi((state >> 32) as i32 % 40 - 20),
                2 | 3 => 0.5,
                _ => 10f32.powf(u * 35.0 - 30.0),
            };
        }
        img
    }

    #[test]
    fn round_trip_is_exact_after_one_quantisation() {
        for (w, h) in [(1, 1), (7, 3), (8, 2), (100, 5), (300, 4)] {
            let img = test_image(w, h, w as u64);
            let path = Path::new("a.hdr");
            let bytes = encode(path, &img).unwrap();
            let once = decode(path, &bytes).unwrap();
            assert_eq!((once.width, once.height), (w, h));
            for (a, b) in img.data.chunks_exact(3).zip(once.data.chunks_exact(3)) {
                let max = a.iter().fold(0f32, |m, v| m.max(*v));
                for k in 0..3 {
                    assert!((a[k] - b[k]).abs() <= max / 128.0, "{a:?} → {b:?}");
                }
            }
            // Values already on the RGBE grid come back bit for bit, bytes too.
            let again = encode(path, &once).unwrap();
            assert_eq!(again, bytes);
            assert_eq!(decode(path, &again).unwrap(), once);
        }
    }

    #[test]
    fn encoder_writes_flat_or_run_length_scanlines() {
        let flat = encode(Path::new("a.hdr"), &Image { width: 2, height: 1, channels: 3, data: vec![1.0; 6] }).unwrap();
        let mut expect = HEADER.to_vec();
        expect.extend(b"-Y 1 +X 2\n");
        expect.extend([128, 128, 128, 129, 128, 128, 128, 129]);
        assert_eq!(flat, expect);
        let rle = encode(Path::new("a.hdr"), &Image { width: 8, height: 1, channels: 3, data: vec![1.0; 24] }).unwrap();
        let mut expect = HEADER.to_vec();
        expect.extend(b"-Y 1 +X 8\n");
        expect.extend([2, 2, 0, 8, 136, 128, 136, 128, 136, 128, 136, 129]);
        assert_eq!(rle, expect);
        // Literal stretches split at 128, runs at 127 (the 3 left over are a run); a pair stays
        // literal.
        let mut out = Vec::new();
        let data: Vec<u8> = (0..130).map(|i| (i % 2) as u8).chain([5; 130]).chain([6, 6]).collect();
        compress_component(&data, &mut out);
        let mut expect = vec![128];
        expect.extend(&data[..128]);
        expect.extend([2, 0, 1, 128 + 127, 5, 128 + 3, 5, 2, 6, 6]);
        assert_eq!(out, expect);
    }

    #[test]
    fn bad_values_and_sizes_are_refused_when_writing() {
        let mut img = Image::new(4, 2, 3);
        img.data[13] = f32::NAN;
        let err = encode(Path::new("out/sky.hdr"), &img).unwrap_err().to_string();
        assert!(err.contains("sky.hdr") && err.contains("pixel (0, 1)") && err.contains("NaN"), "{err}");
        let wrong = Image { width: 4, height: 2, channels: 3, data: vec![0.0; 5] };
        assert!(encode(Path::new("sky.hdr"), &wrong).is_err());
    }

    #[test]
    fn truncated_and_corrupt_files_name_the_file() {
        let img = test_image(40, 6, 9);
        let bytes = encode(Path::new("sky.hdr"), &img).unwrap();
        // Every prefix fails (never panics) and says the file ends early.
        for len in 0..bytes.len() {
            let err = err_of(&bytes[..len]);
            assert!(err.contains("sky.hdr") && err.contains("ends early"), "{len}: {err}");
        }
        // Flipped bytes anywhere give a decoded image or an error, never a panic.
        for i in 0..bytes.len() {
            for v in [0u8, 1, 2, 127, 128, 129, 255] {
                let mut bad = bytes.clone();
                bad[i] = v;
                if let Err(e) = decode(Path::new("sky.hdr"), &bad) {
                    assert!(e.to_string().contains("sky.hdr"), "{e}");
                }
            }
        }
        let cases: [(&[u8], &str); 8] = [
            (b"P6\n", "signature"),
            (b"#?RADIANCE\nFORMAT=32-bit_rle_xyze\n\n-Y 1 +X 1\n", "xyze"),
            (b"#?RADIANCE\n\n+Y 1 +X 1\n\0\0\0\0", "orientation +Y +X"),
            (b"#?RADIANCE\n\n-Y 1 +X\n", "form -Y <height> +X <width>"),
            (b"#?RADIANCE\n\n-Y one +X 1\n", "height \"one\""),
            (b"#?RADIANCE\n\n-Y 20000 +X 20000\n", "more than the"),
            (b"#?RADIANCE\n\n-Y 1 +X 9\n\x02\x02\x00\x08", "marker says 8"),
            (b"#?RADIANCE\n\n-Y 1 +X 8\n\x02\x02\x00\x08\x89\x00", "run reaches pixel 9"),
        ];
        for (bytes, expect) in cases {
            let err = err_of(bytes);
            assert!(err.contains("sky.hdr") && err.contains(expect), "{expect}: {err}");
        }
    }

    #[test]
    fn empty_image_reads_no_pixels() {
        let img = decode(Path::new("a.hdr"), &header(0, 5)).unwrap();
        assert_eq!((img.width, img.height, img.data.len()), (0, 5, 0));
        // No time spent on billions of empty scanlines either.
        let img = decode(Path::new("a.hdr"), &header(0, u32::MAX)).unwrap();
        assert_eq!((img.width, img.height, img.data.len()), (0, u32::MAX, 0));
    }
}

//! Pictures the tests decode: a PNG read back as RGB pixels, with the checks every
//! picture must pass (its size, not blank, not all ink).

use std::collections::HashSet;
use std::path::Path;

/// A decoded RGB picture.
pub struct Picture {
    pub width: u32,
    pub height: u32,
    pub pixels: Vec<[u8; 3]>,
}

impl Picture {
    pub fn read(path: &Path) -> Self {
        let bytes = std::fs::read(path).unwrap();
        let decoder = png::Decoder::new(std::io::Cursor::new(bytes));
        let mut reader = decoder.read_info().expect("a PNG file");
        let mut buf = vec![0; reader.output_buffer_size().unwrap()];
        let info = reader.next_frame(&mut buf).unwrap();
        assert_eq!(info.color_type, png::ColorType::Rgb);
        assert_eq!(info.bit_depth, png::BitDepth::Eight);
        let pixels = buf[..info.buffer_size()]
            .chunks_exact(3)
            .map(|c| [c[0], c[1], c[2]])
            .collect();
        Self {
            width: info.width,
            height: info.height,
            pixels,
        }
    }

    pub fn distinct_colours(&self) -> usize {
        self.pixels.iter().collect::<HashSet<_>>().len()
    }

    /// Fraction of pixels that are not the white background.
    pub fn ink(&self) -> f64 {
        let n = self
            .pixels
            .iter()
            .filter(|p| **p != [255, 255, 255])
            .count();
        n as f64 / self.pixels.len() as f64
    }

    /// Pixels of a saturated colour (not white, grey or black: data colours) in the
    /// columns left of `x`.
    pub fn coloured_left_of(&self, x: u32) -> usize {
        self.pixels
            .chunks_exact(self.width as usize)
            .flat_map(|row| &row[..x as usize])
            .filter(|p| {
                let (lo, hi) = (p.iter().min().unwrap(), p.iter().max().unwrap());
                hi - lo > 80
            })
            .count()
    }

    pub fn count(&self, colour: [u8; 3]) -> usize {
        self.pixels.iter().filter(|p| **p == colour).count()
    }

    /// Checks the size and that the picture is not blank.
    pub fn assert_drawn(&self, width: u32, height: u32) {
        assert_eq!((self.width, self.height), (width, height));
        assert_eq!(self.pixels.len(), (width * height) as usize);
        let distinct = self.distinct_colours();
        assert!(distinct >= 100, "only {distinct} distinct colours");
        let ink = self.ink();
        assert!(
            ink > 0.05,
            "only {:.1} % of the pixels are drawn",
            100.0 * ink
        );
        assert!(ink < 0.95, "{:.1} % drawn: no background left", 100.0 * ink);
    }
}

use vernier::binarize::{Regions, ThresholdMap};
use vernier::GreyImage;
fn bin(g: &GreyImage) -> GreyImage {
    let (w, h) = (g.width() / 2, g.height() / 2);
    let p = g.pixels();
    let mut o = vec![0f32; w * h];
    for r in 0..h {
        for c in 0..w {
            o[r * w + c] = 0.25
                * (p[2 * r * g.width() + 2 * c]
                    + p[2 * r * g.width() + 2 * c + 1]
                    + p[(2 * r + 1) * g.width() + 2 * c]
                    + p[(2 * r + 1) * g.width() + 2 * c + 1]);
        }
    }
    GreyImage::new(w, h, o).unwrap()
}
fn main() {
    let a: Vec<String> = std::env::args().collect();
    let mut img = GreyImage::open(&a[1]).unwrap();
    let n: usize = a[3].parse().unwrap();
    for _ in 0..n {
        img = bin(&img);
    }
    let mut m = ThresholdMap::default();
    m.compute(&img, None);
    eprintln!("floor {}", m.floor());
    let mut out = img.pixels().to_vec();
    let w = img.width();
    for level in [0.5f32, 0.7, 0.3] {
        let mut r = Regions::default();
        r.label(&img, &m, level);
        let mut k = 0;
        for g in &r.regions {
            let bw = (g.bbox[2] - g.bbox[0] + 1) as f64;
            let bh = (g.bbox[3] - g.bbox[1] + 1) as f64;
            if !g.open
                && g.filled_area >= 4.0
                && g.filled_area <= 56.0
                && g.filled_area >= 0.4 * bw * bh
                && bw.max(bh) <= 1.8 * bw.min(bh)
            {
                k += 1;
                for x in g.bbox[0]..=g.bbox[2] {
                    out[g.bbox[1] as usize * w + x as usize] = 1.0;
                }
            }
        }
        eprintln!("level {level}: {k} small");
    }
    GreyImage::new(w, img.height(), out)
        .unwrap()
        .save_png(&a[2], 8)
        .unwrap();
}

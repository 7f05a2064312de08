//! Evaluation of the sparse stage.

#[cfg(test)]
mod tests {
    use crate::vision::sift::{SiftParams, sift};

    #[test]
    #[ignore = "needs /work/shared/data"]
    fn sift_timing() {
        let dir = std::path::PathBuf::from(std::env::var("SDSEM_DATA").unwrap()).join("potamogeton");
        let img = crate::app::rectify::load_gray(&dir.join("pot_02.tif")).unwrap();
        println!("{:?}", img);
        for (dm, sm) in [(0.5, 0.8), (1.0, 0.8), (1.0, 1.6)] {
            let p = SiftParams { delta_min: dm, sigma_min: sm, ..SiftParams::default() };
            let t = std::time::Instant::now();
            let ss = crate::vision::sift::scale_space::ScaleSpace::build(&img, &p);
            let t1 = t.elapsed();
            let ex = crate::vision::sift::detector::detect(&ss, &p);
            let t2 = t.elapsed();
            let kp = sift(&img, &p).unwrap();
            println!("δ_min {dm}: scale space {t1:?}, detect {:?} ({} extrema), total sift {:?}, {} keypoints", t2 - t1, ex.len(), t.elapsed() - t2, kp.len());
        }
    }
}

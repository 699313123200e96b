"""What `stereoseed data fetch` knows of each sample set (:mod:`stereoseed.io.sample_data`):
where its files come from, the SHA-256 of every file it keeps, and the files written from here.

Checksums: a download whose SHA-256 is known here is checked as it arrives. The Middlebury
zips' own checksums are not known here (no copy of the zips on the machine that wrote this),
so each is checked member by member against :attr:`SampleSet.manifest` instead: every file kept
from it has its SHA-256 and size here, taken from the copies in ../shared/data (which SOURCE.txt
says are byte-for-byte the published files). A download with neither is refused: ``None`` below
marks a checksum still to be filled in, from a copy downloaded and checked by hand.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Mapping

__all__ = ["Download", "SampleSet", "SETS"]


@dataclass(frozen=True)
class Download:
    """One file to download. ``kind``: "zip" (unpacked: its members named in the set's manifest
    are kept, found at the manifest's path or under a top folder named like the set), "file"
    (kept at ``dest`` in the set's folder) or "camera" (a Strecha ``.camera`` file, turned into
    the set's calibration; ``dest`` names its image). ``sha256``: of the bytes as served, or None
    where not known here."""

    url: str
    sha256: str | None
    kind: str = "file"
    dest: str = ""


@dataclass(frozen=True)
class SampleSet:
    """A sample set: its downloads, what its folder must hold once unpacked (path -> (SHA-256,
    bytes)), the text files written from here (ring_order.txt) and the conversion it needs
    ("strecha": the published images and .camera files to a Middlebury par file and images
    reduced 4x, as ../shared/data holds them)."""

    name: str
    about: str
    cite: str
    downloads: tuple[Download, ...]
    manifest: Mapping[str, tuple[str, int]] = field(default_factory=dict)
    texts: Mapping[str, str] = field(default_factory=dict)
    convert: str | None = None
    keep_full: bool = False  # "strecha": keep the published images in full/ (as the fountain's copy does)


MIDDLEBURY = "https://vision.middlebury.edu/mview/data/data/"
MIDDLEBURY_CITE = ("S. M. Seitz, B. Curless, J. Diebel, D. Scharstein, R. Szeliski, A Comparison and Evaluation "
                   "of Multi-View Stereo Reconstruction Algorithms, CVPR 2006 (research use)")
# the EPFL multi-view sets as stored in openMVG's evaluation repository, at the commit the copies
# in ../shared/data were taken from (its files are the published images and cameras)
STRECHA = ("https://raw.githubusercontent.com/openMVG/SfM_quality_evaluation/"
           "e2772f8163e7a945f87557949c7d3afd520b7351/Benchmarking_Camera_Calibration_2008/")
STRECHA_CITE = ("C. Strecha, W. von Hansen, L. Van Gool, P. Fua, U. Thoennessen, On Benchmarking Camera "
                "Calibration and Multi-View Stereo for High Resolution Imagery, CVPR 2008 (research use)")
# pyCamSet's test photographs (Apache License 2.0), at the commit named in ../shared/data's SOURCE.txt
PYCAMSET = "https://github.com/rlav440/pyCamSet/raw/b180327/tests/test_data/"
PYCAMSET_CITE = "pyCamSet, https://github.com/rlav440/pyCamSet (Apache License 2.0)"

# the walk around each ring (file numbering is not the ring's order): ../shared/data's ring_order.txt
TEMPLE_ORDER = ("templeSR0005.png templeSR0004.png templeSR0003.png templeSR0014.png templeSR0002.png "
                "templeSR0001.png templeSR0011.png templeSR0010.png templeSR0009.png templeSR0008.png "
                "templeSR0007.png templeSR0006.png templeSR0015.png templeSR0016.png templeSR0012.png "
                "templeSR0013.png")
DINO_ORDER = ("dinoSR0009.png dinoSR0010.png dinoSR0011.png dinoSR0012.png dinoSR0013.png dinoSR0014.png "
              "dinoSR0015.png dinoSR0016.png dinoSR0001.png dinoSR0002.png dinoSR0003.png dinoSR0004.png "
              "dinoSR0005.png dinoSR0006.png dinoSR0007.png dinoSR0008.png")


def _lines(names: str) -> str:
    return "".join(f"{n}\n" for n in names.split())


# ---------------------------------------------------------------------------------------------
# Manifests: SHA-256 and size of every file kept, from ../shared/data's copies

_TEMPLE = {
    "README.txt": ("3d8d3a941c3cacf9532604a13c12a9492de8ee5e46d252b8165b406ff372affa", 1726),
    "templeSR0001.png": ("46e0ead520a16673e32eb36734661b19281fb520e69ff77891216e6971cb9712", 308597),
    "templeSR0002.png": ("d79d27c9491257f90978798584c9a4c3c257dd3dd2b8370ac064ca711d4172af", 294679),
    "templeSR0003.png": ("ee3d3d5efd3239d52422d6f0f4bb090a119f4b2c37e93e91872534a867ad7afc", 192180),
    "templeSR0004.png": ("f79fa50a893aba5850767a458b7d6d6a42e1cfa44182e98737b04f53dac23317", 161764),
    "templeSR0005.png": ("d7877932bbadacfb6fad0d904b1cf75f237219167295824a53397b0f5f6928c0", 182960),
    "templeSR0006.png": ("fad01a491c51f0a1dd52a70d5404c17106d07539132266c45f09d8c4fb25e69b", 268447),
    "templeSR0007.png": ("ffa9e6d19bc780139270315f4c5f673fa7e90497566b680f8fc878657931eec7", 228060),
    "templeSR0008.png": ("1afdc580dd3fc0337b1a056066e952d92a78a2aaf0c2a2dc72c56fc259e95cf6", 215296),
    "templeSR0009.png": ("9b474a1fa539adf06ec362a5e6554705be7cf2a48397f7ab4d8ccbe35dd41843", 247005),
    "templeSR0010.png": ("4b02166d19734e4e1cb0b8d27b7a224ea0b40e2f92e57455b5dd979cb71c647b", 306318),
    "templeSR0011.png": ("e36c68e37eec5426aacddd3b879aa1116c25c8663a6c54654c60f362521b67fd", 310559),
    "templeSR0012.png": ("51d21155a52e90a3904b3f8c8c07a6e45a3e4a029a60f78d732a7e4f5b99186c", 247797),
    "templeSR0013.png": ("6e76cf8da0b19525f2d2e0f51ee42555d4437fd45ae5c2e59d6672b52047d192", 223278),
    "templeSR0014.png": ("dfcfc91feff2878d37be3327e1e1a528d1c7d8c94e76e8b27ede5fda22f4a26d", 265566),
    "templeSR0015.png": ("8a2451cedda6d8d26ca1e0f737e842f4bba3bb47ceb5127bf282f85a18c3ad0d", 280356),
    "templeSR0016.png": ("672e53eb1bd31ed4e2167437dfee55d4c4213edcc42a8f89bda6f48a54581567", 268847),
    "templeSR_ang.txt": ("e8c758495414dc95f09e82231c27d0ee8a0f7a9ec8a36c72bb02c420b22fc4ca", 610),
    "templeSR_par.txt": ("172e2b8957f214aee409add74f09cb4794d5697a2721598d61279bb0afc25388", 5887),
}

_DINO = {
    "README.txt": ("e2ad654d7802ca2f0d911d7b323fffc83eca42fb6eb1d975eb87b867ca1f970a", 2471),
    "dinoSR0001.png": ("1478d5b402e807e806b814541c5024b82802285227f9c8e3a24e0c22903306b4", 260424),
    "dinoSR0002.png": ("f64bce0ac08d40999fd66af76a63cd851e9ac68578e709e543f3cb9d26c5bc86", 276196),
    "dinoSR0003.png": ("16c6650607bafcca055e4046820aa59779311c8b12456e47de3caab0a70225e8", 226812),
    "dinoSR0004.png": ("bda57cb4d8f7629966df1e4ead5cf88802c124d5933272f7c453588a870cd8e9", 195545),
    "dinoSR0005.png": ("22256ac305186da4e07c9f0c46b6401ca1a4592fce4ff1638b734ee8cef6547f", 219224),
    "dinoSR0006.png": ("918f271cd3746ac0a30d81ec98f74c858bbed7cb002199a1d4a9cf5b956f6686", 213632),
    "dinoSR0007.png": ("bd174f4bc1387ea8a47d110cf30e140c797af98da7d332415491053d06110e19", 244982),
    "dinoSR0008.png": ("7add640d4586b268dac447e479a8dce36b61bacd9ea5a0a34574a740f5ee6aff", 283065),
    "dinoSR0009.png": ("03c19cdecc459f1ca50fa3a9caee6af2d46f95128952d5e7b32a1ab240ad5350", 309556),
    "dinoSR0010.png": ("21240efe85000d2aef88718585a2b4164e1710f5276bb6cfee0eeac93ffb04d3", 303835),
    "dinoSR0011.png": ("1e1543ada1b112167c466c0e0176348cd9d444514504d200273bfdb58713917c", 284592),
    "dinoSR0012.png": ("524b45f53e8122457758949692c8f4de4ce229daa574301b49c01ed5aac3cbdb", 214276),
    "dinoSR0013.png": ("40e091db8b0a16297242ea2ff39938bd8149491f6f13292ce770a047cca3cd2c", 181209),
    "dinoSR0014.png": ("14ccad4feaa931c9b24e4aa5c357eb04315e193dc90d7b56a99e21e1cfefdcee", 168902),
    "dinoSR0015.png": ("32333ba547a67abe0c9b2315fd9c20cf64e0c06ea42f2eec1220e51a722adb5c", 188107),
    "dinoSR0016.png": ("15a0056db3a6491b2346ea74a24e9af37db385514110f49ffb661546e6a8defa", 236863),
    "dinoSR_ang.txt": ("8da7618c9c3caa135fea46e5d817a23526109b438e4e863dd6b63119b3fa63c5", 584),
    "dinoSR_good_silhouette_images.txt": ("0e15c8206b18b598cb16f4d6026f9bad52e1b7c2952c7a301043a337f7aba485", 225),
    "dinoSR_par.txt": ("ab951cc4bb0eb11b0af508d4344f84748bee22b02fd3c578bdad87b20ae75002", 5863),
}

_CUBE = {
    "cam0/0.jpg": ("40ff63b9dea3d98a2a5e60add0948c9fcbd84c0b80332c90cf83d5f68f713178", 305171),
    "cam0/1.jpg": ("ce8f322bc142c2e8750033a89806875a6f0235f8acdc91fe595cee9713845ac3", 339399),
    "cam0/2.jpg": ("1bd704b1c5a1c8061f18d99f34b379f5c03eefcf3da305d4dc83cd24f8b939c9", 275288),
    "cam0/3.jpg": ("dabc00e29a715e3d20cbb7998206ea4d9cd1fa995ce79397a685b32f8b74e69c", 277200),
    "cam0/4.jpg": ("30071857577e8afead281956d4e9d2d8b87baf921c6c8c25d61c6187a00a5d67", 310342),
    "cam0/5.jpg": ("a01d5111cb13f8c43b0a920500ff8bab6e633544ca50a5430f21cf926a1bd6a4", 296831),
    "cam0/6.jpg": ("367bca8dc795de401112e0062a5c87d432ce7ec69b76e330ef2e95a4fbef829c", 317507),
    "cam0/7.jpg": ("7ae05d9734cc2550125fd99adcbee57853837c2caf5a141943208342f6b7f53b", 325027),
    "cam0/8.jpg": ("84903044496ae77b6976af36699136033b046bd08af965022f24660d0a28f0bd", 326769),
    "cam0/9.jpg": ("b66aaada9d6b5cb039932d1dbb8710edfc16be5137187118cce9985f7c2d655d", 328955),
    "cam0/10.jpg": ("15edd6e1144e854398e1883daccc98dbeb58e347313f434e36e37fd48d1b6969", 318395),
    "cam0/11.jpg": ("b88ad34ee96fd188ec8a9460e432f281f61ecf1ea69459a80bc0efff468ca48c", 310374),
    "cam0/12.jpg": ("239e36d98e1fd37c089396ecf9223374c06f1c844733574794a701b58916324c", 315035),
    "cam0/13.jpg": ("a0cbada9bed9839c1761f3813559849afd85e89bfb0ca0c61a33414de8c1d2f1", 299124),
    "cam0/14.jpg": ("b99c7c9a5e13756ace4a1c82dcd549cb8d96d5bbc099a36aaae42548c1f7b8fc", 329829),
    "cam0/15.jpg": ("22d766d2ac1c0043cc8a2e2cfa1ef38643689c3e5377bbcc88c71b8118df6171", 371100),
    "cam0/16.jpg": ("b7bdc73ca66b327d40b30e3252c3a4cea0cb00008faea1dc8836681ea2436987", 336955),
    "cam0/17.jpg": ("aa9b6115181ba9af55dd1f6d8ea88973250db4ed1913e228845442dd7676a93e", 350460),
    "cam0/18.jpg": ("7615fec3fa2da67c0b80827c28737da165df035b22241c4f83dff290a177c644", 390720),
    "cam0/19.jpg": ("3dace594cef0bdd2d04382b91c4ab628aecca92b7d4a7984407fda95e3f90045", 397525),
    "cam0/20.jpg": ("d7f6c0ed27ecbd5ad33eca90dfd6080805693bbfba5d184ab513f1740689be88", 384877),
    "cam0/21.jpg": ("d86527af6bd96ac4d56fef1f3916d29deac31d4be44598f8339d45230e54c4c2", 382130),
    "cam0/22.jpg": ("bcf3fb36bf0f4b8f92e2b9733f3edd48b7ca6ef3b8735e8cbfc63296013a359c", 357874),
    "cam0/23.jpg": ("cbe8adf73157ffa9f42fcfc83b295fe2028a1daccab6e1295e3a5e3a50322bda", 329705),
    "cam1/0.jpg": ("5f6d38021c074371c762fb0e4b3e3c52027850fa7139d01f3284d4bae0cf43a0", 345089),
    "cam1/1.jpg": ("6ea653fe12fee8c87ad3522d01a6fc731aa791ae7263d8bcec14f8851d4f912d", 354572),
    "cam1/2.jpg": ("a87ebe043d4014f26349e463149b860455fc864f8ea4b39f60fe7f92034a39a7", 307463),
    "cam1/3.jpg": ("73e7ea4a7e563b042552d1842d5e3acf6212632eed26300c9185eaebf6df74eb", 281528),
    "cam1/4.jpg": ("818605ced62590fb928c8a58541f680e41be5923db020925f3c4501ef1b80652", 341481),
    "cam1/5.jpg": ("dadeff4556b81cfaafd44981239e810b9ebeb00731a46e1d3ee24b7c88c3c0c7", 339751),
    "cam1/6.jpg": ("2782129287b92635ed17db111b245e2f31abea056d3a51690aa7a2577ff94dd8", 355977),
    "cam1/7.jpg": ("0e3f718d573141fe615bb94cd66e6b3e82bfcfc2434a380091536e74eba26e6e", 365682),
    "cam1/8.jpg": ("92ca1adf84c550afe93a0e281160ed81449432c7d7a7c36938af8d87fbe1d428", 383684),
    "cam1/9.jpg": ("22a6e5cc51afbe56191f971910c7799a51bbed6f9e0cc85e602a7d461329641a", 373411),
    "cam1/10.jpg": ("f1af652b577e6ab65731edde62fc24a52ec17c457b98dc6ae711d88f4d067842", 356047),
    "cam1/11.jpg": ("3923a622c9b8f5ba95b88d6de1d94967aeb10aca29f461fa95b62f53619f0c27", 346719),
    "cam1/12.jpg": ("26dd22c4e27b8168a300c6a6853163acaf268692d6494a8ded446d1fe0a05273", 327140),
    "cam1/13.jpg": ("9f5865b102c9bf9b2255d65dcc215acf4388f7c4836267b745d7849ec361bd5d", 322129),
    "cam1/14.jpg": ("a62142b5f111bef4d5d1c31e53a1fc98660867987743138ed35161572e5c3a3a", 330168),
    "cam1/15.jpg": ("4bf34c048d7fa5e7a8e8064cbff4dfe43fcd8ff2277c1753312ada3ff5e7dd9c", 384268),
    "cam1/16.jpg": ("815a7fbfcf7014c9d263ebcddb09849b732f10b153e21b6d21029c82afd45754", 376204),
    "cam1/17.jpg": ("8de2c8d3e948a911f2d8416549f2316b131525129ff237bb9256c9bc7cc9f67f", 395888),
    "cam1/18.jpg": ("4fa0c58011ba58907353e68dd910014113cd08f9fa8d3f03237033e605ab8170", 407574),
    "cam1/19.jpg": ("dbb544bb9ce88676b0979ad98976a11ae54282b1395dd7ced4c20230551a5457", 416835),
    "cam1/20.jpg": ("a5ebb07b7ff83a2433b746b8a5b31f107ad9bed9ae2c3c49424a7e504dcd5fc1", 420651),
    "cam1/21.jpg": ("4529932890a0b48de2e90e008510ea010193383b6642d9a1b1844050f6df45fe", 422007),
    "cam1/22.jpg": ("f8b382d095f11a02a30f3af61804663fb7d7c73c9f10efd2a6e82d43340d523b", 409324),
    "cam1/23.jpg": ("c3b02737d107b41fca413f9edce03d787cf9ad7da5adc0d493c045074b6d30a7", 381106),
}

_FLAT = {
    "cal1.jpg": ("aefa5983bb2f10c092d115a7310e69beecaea1ced34316b5174b379115987e36", 299208),
    "cal2.jpg": ("e0872641bce7b60793406a0f4cff178785085f8adc965151896649ff7efdcf27", 345155),
    "cal3.jpg": ("8cbc56641dd15e5d467a6f762f73c37dee857e24d1b470be9c2137678da148d7", 346019),
    "cal4.jpg": ("c982cd946ef0b09657d5ccfd3c0eb215cbb88ec640f345ae435014795d145b6e", 345550),
    "cal5.jpg": ("f06a36a5060c9f5dcf1622ef1d6672d10517cc7ddbee8f0d7787c7409f11b5f3", 355163),
    "cal6.jpg": ("7d7fa68b5c4b2442c306eb6725965554af7281a950ca11f1591106b71777ad59", 350783),
    "cal7.jpg": ("c69b9196d757f9c5815089ba87ff596132337e851084881219b9757e783b9ea6", 320821),
    "cal8.jpg": ("a69bb30f2730ffadc6fd98318a7a893e9a5395b83243c1fd26a89eea0ef33de7", 332909),
    "cal9.jpg": ("9f5469d24419908f2fe0ea0d37ee51a165aedeaea9c0ab9298730b483119b669", 311043),
    "cal10.jpg": ("10117d4cb6330d0d41b73f2488effb5bcb8770184644d7cc052adeefbe7cbac3", 348370),
    "cal11.jpg": ("101d6de3742ada64f69f40b6af5606e0039935c7e9122a3db34cd9c531a84512", 288814),
    "cal12.jpg": ("37c0710c6118f5b7431d3e158f50a806ce75a762c29f0ad27652d0dfc94f494d", 333991),
    "cal13.jpg": ("289c7b8c0cf80906a76fba9ca99f2d1971427f6c6ccd99ab30e4dd58ac780863", 247446),
    "cal14.jpg": ("70b1117548939770cf9e4036af16e8550becfb9234ddc41cf0abbaab4549150b", 232625),
    "cal15.jpg": ("9f87c92ac918d39647806425554cc1a93266f5e89e3fc6d565ef120e20b373c8", 246097),
    "cal16.jpg": ("bd712dd1587a4cb87e07f152ae7e03999b1f24ddc065f7adc945027063dd9c87", 272530),
    "cal17.jpg": ("250f2b60c66b4637823dbbd05fac49fc2184b9c0cc3bab11466a15b1ff47fb88", 276344),
    "cal18.jpg": ("9a59aed509d63b011fa52c172a057ffb44f72904b4d25de2264ca44cbac0eaf0", 293255),
    "cal19.jpg": ("73f5e1c43f59a214bf9ce01e0eb8808e0c00affee17f73cae8a67a85414e0943", 278794),
    "cal20.jpg": ("8d29666c55d02427a2d552ba34440519dcb8a0757647267aa99e4f4a82378c7b", 245537),
    "cal21.jpg": ("3a2a3526d2fd41121f06612eecfd354a54269e5ba07d2056baf61be2d493b647", 234080),
    "cal22.jpg": ("19f9a35af75f107037dc619ebe4a2d08932ea332f8a9c883ce683614198ac076", 227042),
}

_FOUNTAIN_FULL = {
    "full/0000.jpg": ("dba9a66d5f9fa9d8d6a9fe2646b5107c004f5ad5dd99088eab1f27a661415f91", 2829295),
    "full/0001.jpg": ("3fdd650afdd58eb846255e2b3dace394ecc1d9d46a6ed7a9100f5946b8db99b6", 2932298),
    "full/0002.jpg": ("23f39e085c4d6537849bea22e1082343bf81631fddfbebf707433335d0c64741", 2961594),
    "full/0003.jpg": ("e9694c307343c609e6d8e311bdb0e1d010b4d4482c32e2a5e557535d9194b8c8", 3030989),
    "full/0004.jpg": ("e16a6928525bb25b89641d7866f946ab2348a58138c6b5c6074ff1f2285b8297", 3036204),
    "full/0005.jpg": ("4eaf96a4c9bf128946dfb61744d440966ee220be179529a51925b343dfe17f64", 3024921),
    "full/0006.jpg": ("940af32ff053cb480f3038fdc6b2d1bfa3d3a589f1e08cd29bec736e84594a7f", 3039278),
    "full/0007.jpg": ("852317bdf8c1de049bddd5ad2baa035794f425e955a9e9e7f54ad9885d1b684e", 2973006),
    "full/0008.jpg": ("76374ad0a125d5657743463622ab48c892c96d59b353527477c2dc709b129795", 3008939),
    "full/0009.jpg": ("e69d2b5f718a8600020fa98c8f85b0a6bef540a015368509b1df06120a90a693", 3057054),
    "full/0010.jpg": ("d67a19187030bc48875b82be2610c8327fcf93d29713f62e7f744c074d6758dd", 3056872),
}

_FOUNTAIN_CAMERAS = {
    "0000.jpg": "ecf7d87adb058729193d1d658181fb91007c309b28222ef14538ea6edf6e3b51",
    "0001.jpg": "741c418a0a8c5652724761bb6eb18ffec45fd500ebd9ea95b889085195e26fa2",
    "0002.jpg": "1b4c9a8725f600f587d0a850907797bb5693da0bfaeb01da90bbfb114907c590",
    "0003.jpg": "882dd2ad95aef47b5d5150f74b7d6adffe7ce9718e8700755e04f1e4c2b4291b",
    "0004.jpg": "5d91d297976ae000b3c91808c64df90ca9612919839cf63f4b8dd12ef4990c4e",
    "0005.jpg": "33e3c6a26540b8c42611cd5e4b78dd2f15ef4d1611eb156c888583d04a4045c4",
    "0006.jpg": "dfa3f23eb4079f2aac81fcf1e313f10f0c5f8afab3c9ee6ef3fa8ead00e0aade",
    "0007.jpg": "2103aea75d61d7a977b55c36e09bed2af729b7ada2a963e94a37358574b926a2",
    "0008.jpg": "d1ebbe60304b439d687cb97aad74a306a632ca0605e7052d7a2b52542b295846",
    "0009.jpg": "b286a42c394537604f99d587b154a2b80f78300b1835c27bd7bbe0d73f691f88",
    "0010.jpg": "cac077afad3f72f73fb21ea6fbcf639ca6a950a2ea2919f55471326411e2cc0a",
}


def _strecha(scene: str, n_images: int, images: Mapping[str, tuple[str, int]] | None,
             cameras: Mapping[str, str] | None) -> tuple[Download, ...]:
    """A Strecha scene's published images (to full/) and cameras, with their checksums where
    known here (None: not known, so the set is refused until they are filled in)."""
    names = [f"{i:04d}.jpg" for i in range(n_images)]
    return (tuple(Download(f"{STRECHA}{scene}/images/{n}", images[f"full/{n}"][0] if images else None, "file", f"full/{n}")
                  for n in names)
            + tuple(Download(f"{STRECHA}{scene}/gt_dense_cameras/{n}.camera", cameras[n] if cameras else None,
                             "camera", n) for n in names))


def _files(base: str, manifest: Mapping[str, tuple[str, int]], source_of=lambda p: p) -> tuple[Download, ...]:
    """One download a file of ``manifest``, each from ``base`` + its source path."""
    return tuple(Download(base + source_of(p), sha, "file", p) for p, (sha, _) in manifest.items())


SETS: Mapping[str, SampleSet] = MappingProxyType({s.name: s for s in (
    SampleSet("templeSparseRing", "Middlebury temple, 16 views on a ring, 640x480, par file (the quick start)",
              MIDDLEBURY_CITE, (Download(MIDDLEBURY + "templeSparseRing.zip", None, "zip"),),
              _TEMPLE, {"ring_order.txt": _lines(TEMPLE_ORDER)}),
    SampleSet("dinoSparseRing", "Middlebury dinosaur, 16 views on a ring, 640x480, par file (weak texture)",
              MIDDLEBURY_CITE, (Download(MIDDLEBURY + "dinoSparseRing.zip", None, "zip"),),
              _DINO, {"ring_order.txt": _lines(DINO_ORDER)}),
    SampleSet("strechaFountainP11", "Strecha fountain, 11 views 768x512 (and full/ 3072x2048), par files",
              STRECHA_CITE, _strecha("fountain-P11", 11, _FOUNTAIN_FULL, _FOUNTAIN_CAMERAS),
              _FOUNTAIN_FULL, convert="strecha", keep_full=True),
    # the castle's published images are not on the machine that wrote this: their checksums (and
    # the cameras') are to be filled in before it can be fetched
    SampleSet("strechaCastleP19", "Strecha castle courtyard, 19 views 768x512, par file",
              STRECHA_CITE, _strecha("castle-P19", 19, None, None), convert="strecha"),
    SampleSet("charucoCube", "ChArUco cube photographed by a fixed stereo pair, 2 x 24 views 1920x1080",
              PYCAMSET_CITE, _files(PYCAMSET + "calibration_ccube/", _CUBE), _CUBE),
    SampleSet("charucoFlat", "flat ChArUco board, one camera, 22 views 1280x1024",
              PYCAMSET_CITE, _files(PYCAMSET + "calibration_charuco/1/", _FLAT), _FLAT),
)})

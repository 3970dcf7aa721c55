"""Phase, modulation and temporal unwrapping (docs/conventions.md#phase, #unwrapping).

Four frames with shifts d_k = k pi/2 show I_k = a + b cos(phi - d_k), so
I_0 - I_2 = 2b cos(phi), I_1 - I_3 = 2b sin(phi) and I_0 + I_2 - I_1 - I_3 = 0.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass

import numpy as np

from .kernels import cleaned_residuals, minus_models, noise_rows, phase_counts, trim_rounds, unwrap
from .stats import median, quantile

TWO_PI = 2.0 * np.pi

#: Uniform 8-bit quantisation noise, DN (1/sqrt(12)): the floor of any intensity-noise estimate.
QUANTISATION_NOISE_DN = 1.0 / np.sqrt(12.0)


def wrap_phase(phi: np.ndarray) -> np.ndarray:
    """Wrap radians into [0, 2 pi); an input just below 0 that rounds to 2 pi maps to 0."""
    out = np.mod(phi, TWO_PI)
    out[out >= TWO_PI] = 0.0
    return out


def _wrap_atan2(phi: np.ndarray) -> np.ndarray:
    """Map atan2's (-pi, pi] onto [0, 2 pi) in place (cheaper than np.mod for that range)."""
    phi[phi < 0] += TWO_PI
    phi[phi >= TWO_PI] = 0.0       # -tiny + 2 pi rounds to 2 pi
    return phi


def phase_and_modulation(frames: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Phase, modulation and consistency residual from four quarter-period-shifted frames.

    Parameters
    ----------
    frames : (4, ...) array
        Intensities I_0..I_3 (DN) with shifts 0, pi/2, pi, 3 pi/2.

    Returns
    -------
    phase : array, radians in [0, 2 pi)
        ``mod(atan2(I_1 - I_3, I_0 - I_2), 2 pi)``.
    modulation : array, DN
        Fringe amplitude b = hypot(I_1 - I_3, I_0 - I_2) / 2.
    consistency : array, DN
        I_0 + I_2 - I_1 - I_3; zero up to noise when the display showed each frame completely.
    """
    frames = np.asarray(frames)
    if frames.shape[0] != 4:
        raise ValueError(f"frames must hold 4 phase steps along axis 0, got shape {frames.shape}")
    if frames.dtype in (np.uint8, np.uint16) and frames[0].size > 0:
        return _phase_and_modulation_counts(frames)
    # Integer counts convert exactly to float32, and float32 phase resolves 1e-6 rad: ample, and faster.
    work = np.float32 if np.issubdtype(frames.dtype, np.integer) and frames.itemsize <= 2 else np.float64
    i0, i1, i2, i3 = (frames[k].astype(work) for k in range(4))
    s = i1 - i3
    c = i0 - i2
    phase = _wrap_atan2(np.arctan2(s, c))
    modulation = 0.5 * np.hypot(s, c)
    consistency = (i0 + i2) - (i1 + i3)
    return phase, modulation, consistency


def _phase_and_modulation_counts(frames: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`phase_and_modulation` of 8- or 16-bit counts in one compiled pass over the pixels
    (:func:`~.kernels.phase_counts`), from the counts without converting whole frames.

    With s = I_1 - I_3 and c = I_0 - I_2 (whole counts, exact):

    * phase: atan2(s, c) wrapped into [0, 2 pi), evaluated in float64 and rounded once to float32 (within
      half a float32 step of the exact value; s = 0 gives 0 where c >= 0 and pi where c < 0). It differs
      from the general path's float32 ``atan2(s, c) + 2 pi`` by at most one float32 step (4.8e-7 rad, a
      thousandth of the phase noise of 1 DN on 50 DN of modulation): checked over every 8-bit (s, c);
    * modulation: sqrt(s^2 + c^2) / 2, the sum exact in float64 and its square root rounded to float32:
      the correctly rounded hypot, as the C library's float hypot computes it;
    * consistency: (I_0 + I_2) - (I_1 + I_3) in integers, exact.
    """
    shape = frames.shape[1:]
    flat = np.ascontiguousarray(frames).reshape(4, -1)
    phase, modulation, consistency = (np.empty(flat.shape[1], dtype=np.float32) for _ in range(3))
    phase_counts(flat, phase, modulation, consistency)
    return phase.reshape(shape), modulation.reshape(shape), consistency.reshape(shape)


#: Residuals beyond this many standard deviations are trimmed from the noise variance (iteratively).
TRIM_SIGMAS = 4.5
#: Largest number of residuals the noise and harmonic estimates use (a fixed stride beyond it).
MAX_NOISE_SAMPLES = 200_000


def _stride(r: np.ndarray) -> np.ndarray:
    """A fixed stride of at most :data:`MAX_NOISE_SAMPLES` elements: deterministic and fast."""
    return r[:: max(1, -(-r.size // MAX_NOISE_SAMPLES))]


def trimmed_std(r: np.ndarray, trim_sigmas: float = TRIM_SIGMAS, rounds: int = 50) -> float:
    """Standard deviation of *r* with outliers trimmed, consistent for Gaussian data.

    Unlike the median absolute deviation, this keeps its meaning on integer-valued residuals (whose
    median absolute deviation can only take a few values): the variance of the values within
    ``trim_sigmas`` standard deviations, divided by that truncated Gaussian's variance fraction, iterated
    from the 68th percentile of |r| until the kept set stops changing.
    """
    r = np.asarray(r, dtype=np.float64).ravel()
    if r.size == 0:
        return 0.0
    about = median(r)
    a = np.abs(r - about)
    s = max(quantile(a, 0.6827), 0.5)
    c = float(trim_sigmas)
    # Variance of a standard Gaussian truncated to |z| <= c, relative to 1.
    frac = math.erf(c / math.sqrt(2.0))
    shrink = 1.0 - 2.0 * c * np.exp(-0.5 * c * c) / np.sqrt(2.0 * np.pi) / frac
    return float(trim_rounds(r, a, c, s, float(shrink), int(rounds), about))


def intensity_noise_dn(consistency: np.ndarray, quantised: bool = True) -> float:
    """Per-frame intensity noise (DN) from consistency residuals I_0 + I_2 - I_1 - I_3 alone.

    The residual of four independent frames with noise sigma has standard deviation
    2 sqrt(sigma^2 + q^2), q^2 = 1/12 DN^2 being the variance of rounding to whole counts (exact on average
    over pixels whose true values have uniformly spread fractions). The trimmed standard deviation keeps
    the estimate immune to the few pixels a half-drawn frame spoils. With *quantised* the rounding
    variance is removed, so the result estimates the camera's own noise; 0 when rounding explains all.
    Residuals carrying a display nonlinearity must be cleaned first (:func:`frame_noise`).
    """
    r = _stride(np.asarray(consistency, dtype=np.float64).ravel())
    if r.size == 0:
        return 0.0
    var = (trimmed_std(r) / 2.0) ** 2 - (QUANTISATION_NOISE_DN ** 2 if quantised else 0.0)
    return float(np.sqrt(max(var, 0.0)))


def _power_law_table(exponents: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Second-harmonic ratio and largest four-step phase error (rad) of full-depth fringes seen through a
    power-law response I = (1 + cos theta)^g, for each exponent g (the model behind the phase-error
    estimate of :func:`frame_noise`)."""
    phi = np.linspace(0.0, TWO_PI, 720, endpoint=False)
    ratios, errors = [], []
    for g in exponents:
        i0, i1, i2, i3 = ((1.0 + np.cos(phi - k * np.pi / 2)) ** g for k in range(4))
        s, c = i1 - i3, i0 - i2
        b = 0.5 * np.hypot(s, c)
        x = b * np.cos(2.0 * phi)
        ratios.append(float(x @ (i0 + i2 - i1 - i3)) / float(x @ x) / 4.0)
        errors.append(float(np.abs(np.angle(np.exp(1j * (np.arctan2(s, c) - phi)))).max()))
    return np.array(ratios), np.array(errors)


_EXPONENTS = np.linspace(0.25, 4.0, 301)
#: ``_power_law_table(_EXPONENTS)`` (second-harmonic ratios, largest phase errors in rad), computed once and
#: written here: computing it took 0.03 s of every analysing command's start (tests/measure/test_phase.py
#: recomputes it).
_RATIOS = np.array([
    -0.2966785822877284, -0.29124888818746136, -0.2858225299471309, -0.28039966158517643, -0.27498068006243115,
    -0.2695661589205047, -0.2641567992349053, -0.2587533929598041, -0.2533567952589249, -0.24796790343320077,
    -0.2425876407467355, -0.23721694392903375, -0.23185675346430032, -0.22650800601395082, -0.22117162848675584,
    -0.21584853339262736, -0.21053961520476017, -0.20524574752015529, -0.19996778085704678,
    -0.19470654096406248, -0.189462827543338, -0.18423741331061497, -0.1790310433312868, -0.17384443458362478,
    -0.16867827570994, -0.16353322692386688, -0.15840992004779345, -0.1533089586590812, -0.14823091832738974,
    -0.1431763469283651, -0.1381457650213202, -0.13313966628046098, -0.12815851797078037, -0.12320276146103512,
    -0.11827281276728709, -0.11336906312138098, -0.10849187955947798, -0.10364160552639268,
    -0.09881856149201843, -0.09402304557658298, -0.08925533418187215, -0.08451568262590019, -0.0798043257788041,
    -0.07512147869799922, -0.07046733726086489, -0.0658420787934316, -0.061245862693721176,
    -0.05667883104855612, -0.05214110924279418, -0.047632806560080086, -0.04315401677431776,
    -0.03870481873117696, -0.034285276919041076, -0.029895442028890776, -0.025535351502697434,
    -0.021205030069970512, -0.01690449027216948, -0.01263373297474933, -0.008392747866661977,
    -0.004181513947186042, 6.26785989026199e-18, 0.004151834945544559, 0.008274041165956949,
    0.01236667780792499, 0.016429812465357994, 0.0204635207690774, 0.02446788598904604, 0.028442998649010575,
    0.03238895615341141, 0.03630586242639466, 0.040193827562750986, 0.04405296749058775, 0.04788340364553261,
    0.051685262656257024, 0.05545867604109607, 0.0592037799155399, 0.06292071471035991, 0.06660962490013238,
    0.0702706587419176, 0.0739039680238469, 0.07750970782337369, 0.0810880362749372, 0.08463911434679197,
    0.08816310562675349, 0.09166017611661319, 0.09513049403497549, 0.09857422962827246, 0.10199155498971456,
    0.10538264388593618, 0.10874767159110119, 0.11208681472823308, 0.11540025111754135, 0.11868815963151677,
    0.12195072005657445, 0.12518811296102592, 0.128400519569167, 0.13158812164127207, 0.13475110135928944,
    0.1378896412180395, 0.14100392392171737, 0.1440941322855125, 0.1471604491421565, 0.15020305725321967,
    0.1532221392249794, 0.1562178774286884, 0.15919045392507605, 0.16214005039292037, 0.1650668480615335,
    0.1679710276470071, 0.1708527692920695, 0.1737122525094107, 0.17654965612833542, 0.17936515824460922,
    0.18215893617336712, 0.18493116640495724, 0.18768202456359778, 0.19041168536872824, 0.19312032259894027,
    0.19580810905837856, 0.19847521654550307, 0.20112181582411112, 0.20374807659651845, 0.20635416747880395,
    0.20894025597802518, 0.21150650847131508, 0.21405309018677432, 0.21658016518607537, 0.21908789634869968,
    0.2215764453577303, 0.22404597268712556, 0.22649663759040362, 0.22892859809066854, 0.23134201097191245,
    0.23373703177153024, 0.23611381477398607, 0.23847251300557343, 0.240813278230212, 0.24313626094622856,
    0.24544161038406911, 0.24772947450489255, 0.25, 0.2522533322910519, 0.2544896155310308, 0.25670899260590657,
    0.25891160513696554, 0.261097593483764, 0.2632670967476679, 0.26542025277594783, 0.26755719816638984,
    0.2696780682723953, 0.27178299720853466, 0.27387211785652804, 0.2759455618716239, 0.27800345968934886,
    0.2800459405326034, 0.28207313241907767, 0.28408516216896523, 0.28608215541295223, 0.28806423660046043,
    0.2900315290081244, 0.2919841547484824, 0.29392223477886326, 0.29584588891045266, 0.2977552358175212,
    0.29965039304679686, 0.301531477026971, 0.30339860307831934, 0.3052518854224263, 0.30709143719200027,
    0.3089173704407665, 0.3107297961534261, 0.31252882425567163, 0.31431456362424615, 0.31608712209703954,
    0.31784660648320906, 0.31959312257331796, 0.3213267751494834, 0.3230476679955243, 0.3247559039071044,
    0.3264515847018608, 0.3281348112295137, 0.3298056833819505, 0.33146430010327654, 0.3331107593998318,
    0.3347451583501626, 0.33636759311494874, 0.33797815894687827, 0.3395769502004674, 0.3411640603418213,
    0.34273958195833193, 0.3443036067683107, 0.3458562256305511, 0.3473975285538201, 0.34892760470627493,
    0.35044654242480333, 0.35195442922428427, 0.35345135180676845, 0.35493739607057495, 0.3564126471193043,
    0.3578771892707663, 0.3593311060658179, 0.360774480277117, 0.36220739391778256, 0.363629928249967,
    0.3650421637933378, 0.3664441803334653, 0.36783605693012084, 0.36921787192548006, 0.37058970295223487,
    0.3719516269416122, 0.3733037201312978, 0.37464605807326895, 0.37597871564153235, 0.37730176703976953,
    0.37861528580888903, 0.37991934483448536, 0.3812140163542068, 0.38249937196502964, 0.38377548263044153,
    0.3850424186875339, 0.38630024985400235, 0.38754904523505895, 0.38878887333025297, 0.39001980204020437,
    0.39124189867324793, 0.3924552299519906, 0.39365986201978176, 0.3948558604470976, 0.39604329023784,
    0.39722221583555234, 0.39839270112954905, 0.39955480946096555, 0.4007086036287245, 0.4018541458954215,
    0.4029914979931311, 0.40412072112913316, 0.40524187599156164, 0.4063550227549754, 0.4074602210858537,
    0.40855753014801516, 0.409647008607963, 0.4107287146401571, 0.4118027059322121, 0.41286903969002625,
    0.41392777264283775, 0.41497896104821197, 0.41602266069696076, 0.41705892691799284, 0.4180878145830985,
    0.41910937811166815, 0.4201236714753454, 0.421130748202618, 0.4221306613833431, 0.42312346367321285,
    0.4241092072981586, 0.4250879440586934, 0.4260597253341968, 0.42702460208714066, 0.4279826248672578,
    0.42893384381565336, 0.42987830866886184, 0.4308160687628475, 0.43174717303695265, 0.43267167003779244,
    0.4335896079230954, 0.4345010344654959, 0.4354059970562733, 0.43630454270904345, 0.4371967180633988,
    0.43808256938850304, 0.4389621425866364, 0.4398354831966954, 0.44070263639764634, 0.4415636470119336,
    0.44241855950884434, 0.4432674180078286, 0.44411026628177774, 0.4449471477602593, 0.44577810553271197,
    0.4466031823515977, 0.44742242063551696, 0.44823586247228075, 0.449043549621947, 0.4498455235198174,
    0.4506418252793966, 0.45143249569531524, 0.45221757524621686, 0.4529971040976084, 0.4537711221046763,
    0.45453966881506785, 0.4553027834716394, 0.4560605050151702, 0.456812872087044, 0.45755992303189935,
    0.4583016959002466, 0.4590382284510551, 0.459769558154309, 0.4604957221935338, 0.4612167574682924,
    0.4619327005966528, 0.4626435879176267])
_PHASE_ERRORS = np.array([
    0.09832533837482593, 0.09597844053388703, 0.09364869664483844, 0.09133666884392141, 0.08904290609659316,
    0.0867679438661548, 0.08451230380666329, 0.08227649348024332, 0.08006100609885689, 0.0778671962358084,
    0.0756967686712078, 0.07354774263835015, 0.07142056822462298, 0.06931567993396445, 0.0672334965553465,
    0.06517442105565621, 0.0631388404965354, 0.061127125974713904, 0.059139632585303054, 0.05717669940748291,
    0.055238649511973464, 0.05332578998963847, 0.05143841200054513, 0.04957679084276225, 0.04774118604016778,
    0.04593184144849551, 0.04414898537885062, 0.04239283073788935, 0.04066357518386685, 0.038961401297721104,
    0.037286476768384945, 0.0356389545914875, 0.03401897328062666, 0.032426657090380395, 0.030862116250247842,
    0.029325447208695253, 0.027816732886515295, 0.02633604293870251, 0.02488343402406936, 0.023458950081837404,
    0.022062622614468896, 0.02069447097599688, 0.019354502665157123, 0.018042713622637117, 0.016759088531767663,
    0.015503601122024426, 0.01427621447472063, 0.013076881330290146, 0.011905544396599656, 0.010762136657741084,
    0.009646581682783517, 0.008558793933992814, 0.007498679074050773, 0.006466134271825051,
    0.005461048506276957, 0.004483302868109962, 0.003532770858789757, 0.002609318686591667,
    0.0017128055593524927, 0.0008430839736315537, 4.440892098500626e-16, 0.000816606435786349,
    0.0016069012759729836, 0.002371056058554255, 0.0031092476497758485, 0.003821683921200215,
    0.0045086293947289805, 0.0051702107132725285, 0.005806622223885284, 0.006418062245414912,
    0.007004732839953176, 0.007566839589615104, 0.008104591378703918, 0.008618200181303126,
    0.009107880854321482, 0.009573850936013062, 0.010016330449970101, 0.010435541714600038, 0.01083170915805498,
    0.011205059138607922, 0.011555819770436206, 0.011884220754772667, 0.012190493216392786,
    0.012474869545364054, 0.012737583244021767, 0.01297886877909058, 0.01319896143889412, 0.013398097195572056,
    0.01357651257223782, 0.013734444514975654, 0.013872130269617202, 0.013989807263192544, 0.014087712989969494,
    0.014166084901992693, 0.014225160304026008, 0.014265176252799239, 0.01428636946046804, 0.01428897620218159,
    0.014273232227667765, 0.014239372676723594, 0.014187631998531704, 0.014118243874676506,
    0.014031906786198898, 0.013928419305579776, 0.013807971772461758, 0.013670792188831027,
    0.013517107489532998, 0.013347143486162706, 0.013161124813893255, 0.012959274881155392,
    0.012741815822073366, 0.012508968451573321, 0.012260952223082345, 0.011997985188721106,
    0.011720283961921596, 0.011428063682379166, 0.011121537983255882, 0.010800918960569806,
    0.010466417144674278, 0.010118241473772271, 0.00975659926937189, 0.009381696213625614, 0.008993736328477308,
    0.008592921956545286, 0.008179453743681897, 0.007753530623135529, 0.007315349801257231,
    0.006865106744690208, 0.006402995168976379, 0.005929207028525707, 0.005443932507895044,
    0.004947360014309787, 0.00443967617138602, 0.003921065813995451, 0.003391711984223523, 0.002851839562701098,
    0.002301614765777704, 0.0017411444694277695, 0.0011706034994916298, 0.0005901649131581643,
    4.440892098500626e-16, 0.000599721716204616, 0.0012088324749101923, 0.0018271662755428902,
    0.0024545588735629623, 0.003090847775893945, 0.0037358722357530246, 0.004389473246901221,
    0.005051493537363538, 0.005721777562627284, 0.006400171498363695, 0.007086523232691345,
    0.007780682358005353, 0.008482500162410478, 0.009191829620764235, 0.009908525385367217,
    0.010632443776318357, 0.011363442771552545, 0.012101381996590522, 0.012846122714008668,
    0.013597527812662125, 0.014355461796663005, 0.015119790774145403, 0.015890382445824726,
    0.016667106093375208, 0.017449832567627978, 0.01823843427662133, 0.01903278517350262, 0.019832760744302735,
    0.020638237995594475, 0.021449715517324355, 0.022266623491403757, 0.023088729093273305, 0.02391591572444909,
    0.024748068228334308, 0.025585072877755157, 0.026426817362443587, 0.027273190776480296, 0.02812408360570575,
    0.028979387715103465, 0.029838996336170067, 0.030702804054270304, 0.03157070679599296, 0.032442601816505844,
    0.033318387686921434, 0.03419796428167945, 0.035081232765943084, 0.0359680955830284, 0.03685845644185928,
    0.03775222030445604, 0.03864929337346747, 0.0395495830797439, 0.04045299806995508, 0.04135944819426263,
    0.042268844494045575, 0.0431810991896808, 0.044096125668385854, 0.04501383847212573, 0.04593415328558351,
    0.046856986924199706, 0.04778225732228261, 0.0487098835211901, 0.04963978565758811, 0.05057188495178144,
    0.05150610369612998, 0.052442365243534426, 0.053382321388042685, 0.05432429665264606, 0.05526815345604463,
    0.05621381942911821, 0.05716122319838111, 0.058110294375124626, 0.059060963544648425, 0.06001316225556887,
    0.06096682300921887, 0.06192187924913073, 0.06287826535060548, 0.063835916610367, 0.06479476923630667,
    0.06575476033731364, 0.06671582791319276, 0.06767791084466904, 0.0686409488834838, 0.0696048826425739,
    0.07056965358634469, 0.07153520402102512, 0.07250147708511559, 0.07346841673992133, 0.07443596776017561,
    0.07540407572474564, 0.07637268700743371, 0.07734174876785829, 0.07831120894242562, 0.07928101623538697,
    0.08025112010998336, 0.08122147077967258, 0.08219201919944676, 0.08316271705722998, 0.08413351676536493,
    0.08510437145218017, 0.08607523495364269, 0.08704606180509408, 0.08801821012283308, 0.08899181886020749,
    0.08996532327824866, 0.09093868061065027, 0.09191184874466553, 0.09288478621340902, 0.09385745218824293,
    0.09482980647123387, 0.09580180948768957, 0.09677342227877819, 0.09774460649421025, 0.09871532438501028,
    0.09968553879635536, 0.10065521316048784, 0.10162431148970466, 0.10259279836941927, 0.10356063895129505,
    0.10452779894644992, 0.1054942446187346, 0.10645994277808034, 0.10742486077391408, 0.10838896648864949,
    0.10935222833124073, 0.11031461523080632, 0.1112760966303232, 0.11223664248038313, 0.11319622323302017,
    0.11415480983560158, 0.1151123737247837, 0.11606888682053348, 0.11702432152021355, 0.11797865069273009,
    0.11893184767274725, 0.11988388625495651, 0.12083474068841468, 0.12178438567094066, 0.12273279634357094,
    0.12368407189389849, 0.12463416864367206, 0.12558302285035453, 0.12653061123090148, 0.12747691091470095,
    0.12842189943844165, 0.12936555474103464, 0.13030785515859503, 0.13124877941947277, 0.13218830663934142,
    0.133126416316341, 0.13406308832627215, 0.13499830291784543, 0.13593204070798023, 0.13686428267715778,
    0.13779501016482484, 0.13872420486484696, 0.13965184882101347, 0.14057792442259087, 0.14150241439992747,
    0.14242530182010452, 0.14334657008263663])


def phase_error_from_harmonic(ratio: float) -> float:
    """Largest four-step phase error (rad) that a power-law response with this second-harmonic ratio
    (second-harmonic amplitude over the fundamental's, signed) gives on full-depth fringes."""
    ratio = float(np.clip(ratio, _RATIOS[0], _RATIOS[-1]))
    return float(np.interp(ratio, _RATIOS, _PHASE_ERRORS))


@dataclass(frozen=True)
class FrameNoise:
    """What the four-step residuals say about the capture: noise, and a display response left nonlinear.

    A display whose response is not linear adds harmonics to every fringe. In I_0 + I_2 - I_1 - I_3 the
    fundamental cancels but the second harmonic c_2 cos(2 (phi - d_k) + psi) adds up to
    4 c_2 cos(2 phi + psi): a residual that follows the phase, which noise does not. It is fitted per set
    as r = alpha + b (beta cos 2 phi + gamma sin 2 phi) [+ delta w] (alpha, delta per set: room light or
    exposure changing between frames, w the pixel's white - dark; beta, gamma shared by the sets) and
    removed before the noise is estimated (with the sixth harmonic, which survives the residual too).

    Attributes
    ----------
    noise_dn : float
        Per-frame camera noise, DN, rounding to whole counts removed (see :func:`intensity_noise_dn`).
    frame_noise_dn : float
        Per-frame noise including rounding, sqrt(noise^2 + 1/12), DN: what phases and consistency see.
    harmonic_ratio : float
        The second harmonic's amplitude over the fundamental's (0 for a linear response; about 0.28 for a
        display with gamma 2.2 left uncorrected), fitted over all sets together.
    signed_harmonic_ratio : float
        The same, positive when the response bends upward (gamma above 1), negative when downward.
    phase_error_rad : float
        Largest phase error the response gives the four-step phase, rad: as the capture shows it between
        its coarse and fine sets (:func:`phase_error_between_periods`, ``phase_error_from`` "periods"),
        or, where they cannot tell, from the second harmonic assuming a power law over the fringe's full
        depth (:func:`phase_error_from_harmonic`, "harmonic").
    residuals : list of arrays
        Each set's consistency residual with its fitted harmonic and offset removed, DN.
    phase_error_rms_rad, phase_error_u_rad : float or None
        The phase error's RMS over a period and the standard uncertainty of ``phase_error_rad``, rad (from
        the period sets; None from the harmonic).
    phase_error_from : str
        "periods" or "harmonic".
    harmonic_offsets_dn : tuple of float
        Each set's mean of the fitted harmonic over its pixels, DN (x sets, then y sets): the part of a set's
        mean residual that is the display's static response, not a brightness change between its frames.
        A facet that sees a short stretch of a coarse fringe sees nearly one phase, so its harmonic
        4 c_2 cos(2 phi + psi) does not average out over the pixels: on the population's dish stations
        (display gamma 2.227 against the table's 2.2) it made every set's mean 1.2-2.1 DN with the room
        light steady, the frame-to-frame brightness read as 0.8 DN instead of 0.05, and the slope RMS
        values' U twice their errors' spread (:func:`~.uncertainty.frame_brightness_dn` takes it out).
    """

    noise_dn: float
    frame_noise_dn: float
    harmonic_ratio: float
    signed_harmonic_ratio: float
    phase_error_rad: float
    residuals: list
    phase_error_rms_rad: float | None = None
    phase_error_u_rad: float | None = None
    phase_error_from: str = "harmonic"
    harmonic_offsets_dn: tuple = ()

    def with_period_error(self, measured: "PeriodPhaseError | None") -> "FrameNoise":
        """This estimate with the phase error the period sets show (:func:`phase_error_between_periods`),
        when they show one; unchanged otherwise."""
        if measured is None:
            return self
        return dataclasses.replace(self, phase_error_rad=measured.max_rad, phase_error_rms_rad=measured.rms_rad,
                                   phase_error_u_rad=measured.u_rad, phase_error_from="periods")


def frame_noise(phases, modulations, residuals, level=None, pool=None) -> FrameNoise:
    """Noise and display nonlinearity from the four-step sets of one capture.

    Parameters
    ----------
    phases, modulations, residuals : sequences of arrays
        Per four-step set, as :func:`phase_and_modulation` returns them (rad, DN, DN), same pixels.
    level : array, optional
        Each pixel's brightness (white - dark, DN), the same pixels. Room light or exposure changing
        between frames changes each pixel in proportion to its brightness: with *level* that part is
        fitted too. (Not the mean of the fringe frames: a half-drawn frame would leak into it.)
    pool : executor, optional
        Where half of the sets' fit samples, scatters and cleaned residuals are formed beside the other
        half (each set's arithmetic is the same on any thread).

    Returns
    -------
    FrameNoise
    """
    n_sets = len(residuals)
    if n_sets == 0:
        return FrameNoise(0.0, QUANTISATION_NOISE_DN, 0.0, [], 0.0, [])
    level = None if level is None else np.asarray(level).ravel()
    per_set = 1 if level is None else 2

    def sample(k):
        """Set k's regressors on every stride-th pixel (double precision): its own offset (and mean level),
        then the shared harmonics (the sixth survives the residual too: its sign alternates with the
        step), and its residuals (:func:`~.kernels.noise_rows`, one compiled pass)."""
        r = np.asarray(residuals[k]).ravel()
        stride = max(1, -(-r.size * n_sets // MAX_NOISE_SAMPLES))
        return noise_rows(phases[k], modulations[k], r, level, stride)

    samples = _map_halves(pool, sample, range(n_sets))

    def joint_fit(good):
        """One fit over the *good* sets: each its own offset (and level term), the harmonics shared. A set
        whose pixels see only part of a fringe (coarse periods over a small reflected footprint) cannot
        tell a harmonic from an offset on its own; together the sets can. Returns the shared harmonic
        coefficients and every set's own coefficients (those of the others fitted with the harmonic fixed)."""
        coef = _block_lstsq([samples[k] for k in good], first_blocks)
        n_own = per_set * len(good)
        harmonic, own_coefs = coef[n_own:], []
        for k in range(n_sets):
            if k in good:
                j = good.index(k)
                own_coefs.append(coef[per_set * j:per_set * (j + 1)])
            else:
                own, shared, r = samples[k]
                own_coefs.append(_robust_lstsq(own, minus_models(r, shared, harmonic), stride=False))
        return harmonic, own_coefs

    # A set spoiled by a half-drawn frame keeps a large scatter about the shared fit (its error follows
    # the fundamental, and the other sets do not share it): the worst such set is left out and the fit
    # repeated, one set at a time (a spoiled set also pulls the shared terms, so others look worse at first).
    good = list(range(n_sets))
    first_blocks: dict = {}      # each set's sums over all its samples: the same in every refit
    while True:
        harmonic, own_coefs = joint_fit(good)
        scatter = _map_halves(pool, lambda k: trimmed_std(minus_models(samples[k][2], samples[k][1], harmonic,
                                                                       samples[k][0], own_coefs[k])), range(n_sets))
        worst = max(good, key=lambda k: scatter[k])
        if len(good) == 1 or scatter[worst] <= 2.0 * min(scatter[k] for k in good):
            break
        good.remove(worst)
    def clean(k):
        return cleaned_residuals(residuals[k], phases[k], modulations[k], level, harmonic, own_coefs[k])

    cleaned = _map_halves(pool, clean, range(n_sets))
    # r = 4 c_2 cos(2 phi + psi): the ratio c_2 / b, signed by the cosine part (power laws have psi = 0, pi).
    ratio = 0.25 * float(np.hypot(harmonic[0], harmonic[1])) * (1.0 if harmonic[0] >= 0 else -1.0)
    noise = intensity_noise_dn(np.concatenate([_stride(cleaned[k]) for k in good]))
    # the shared harmonic's mean over each set's (sampled) pixels: static, not a brightness change
    offsets = tuple(float(np.mean(harmonic @ samples[k][1])) if samples[k][1].shape[1] else 0.0
                    for k in range(n_sets))
    return FrameNoise(noise_dn=noise, frame_noise_dn=float(np.hypot(noise, QUANTISATION_NOISE_DN)),
                      harmonic_ratio=abs(ratio), signed_harmonic_ratio=ratio,
                      phase_error_rad=phase_error_from_harmonic(ratio), residuals=cleaned,
                      harmonic_offsets_dn=offsets)


#: Harmonics kept of the phase error the fringes' rounding to whole commands leaves (:func:`drawn_phase_error`):
#: multiples of 4 up to this, and up to a sixth of a period's display pixels (a camera pixel's footprint on
#: the screen, a pixel or so, and the decoded position's own error, a few tenths of one, blur the finer ripple).
DRAWN_MAX_HARMONIC = 64
#: Samples over one period of :func:`drawn_phase_error`'s table.
DRAWN_TABLE_SIZE = 2048


@functools.lru_cache(maxsize=32)
def drawn_phase_error(lut: tuple, floor_level: float, max_level: float, samples_per_period: float,
                      footprint_px: tuple = (0.0, 0.0)) -> tuple | None:
    """The four-step phase error of a fringe set as the display draws it and a camera pixel sees it, over one
    period (rad).

    The station draws a set's fringes through its radiometric record's lookup table (*lut*, a tuple: command / 255
    against linear response level 0..1, :mod:`~sofast_station.devices.renderer`) and rounds each display
    pixel's command to a whole 8-bit value. With *samples_per_period* (a whole number n) display pixels per
    period, pixel i shows phase 2 pi (i + 1/2) / n in every period, so its rounding error, and the phase
    error e_i a four-step phase makes of the four rounded levels (seen through the response the table
    inverts), repeat with the period: a fixed ripple of a few tenths of a mrad per harmonic, all multiples
    of 4. It differs from set to set (n differs: the coarse set samples the same rounding function 4 times
    as densely), so the coarse and fine sets' disagreement cannot measure it
    (:func:`phase_error_between_periods` takes it as known), and on a nearly flat facet far from the
    screen its projection on a straight line over the patch the facet reflects reads as focal power
    (issue 47: f 50-110 ppm off at 10 m). Returned as the ripple's harmonics up to
    :data:`DRAWN_MAX_HARMONIC` (and n / 6) sampled at phases 2 pi j / M, M = :data:`DRAWN_TABLE_SIZE`;
    None when n is not a whole number of at least 8 (the ripple does not repeat with the phase). Kept for
    the process (the same record and display give the same table every capture).

    A camera pixel integrates the display over its footprint on the screen, a parallelogram whose edges span
    *footprint_px* = (a, b) display pixels along the fringes' axis (:func:`pixel_footprint_px`): harmonic k
    (k cycles over n display pixels) reaches the phase multiplied by sinc(k a / n) sinc(k b / n). Far from
    the screen this is no detail: a pixel of the population's heliostat station (400 x 300 camera, 4 m from a
    1.1 mm pitch screen) spans about 9.7 display pixels, and the ripple's strongest harmonics of the
    16-period set (k 14 to 24 of n = 150) reach it at a tenth or less; the table of a point's view took them
    off at full depth, and left 28 um RMS of ripple in the positions of a twin that integrates the footprint
    (issue 47, docs/method.md "Nearly flat facets far from the screen"). (0, 0): a point's view.
    """
    n_float = float(samples_per_period)
    n = int(round(n_float))
    if n < 8 or abs(n_float - n) > 1e-9:
        return None
    lut = np.asarray(lut, dtype=np.float64)
    grid = np.linspace(0.0, 1.0, lut.size)
    phi = 2.0 * np.pi * (np.arange(n) + 0.5) / n
    seen = []
    for k in range(4):
        level = floor_level + (max_level - floor_level) * 0.5 * (1.0 + np.cos(phi - 0.5 * np.pi * k))
        command = np.floor(255.0 * np.interp(level, grid, lut) + 0.5)     # the shader's rounding
        seen.append(np.interp(command / 255.0, lut, grid))
    error = np.angle(np.exp(1j * (np.arctan2(seen[1] - seen[3], seen[0] - seen[2]) - phi)))
    top = min(DRAWN_MAX_HARMONIC, n // 6)
    ks = np.arange(1, top + 1)
    # e(phi) = mean + sum_k a_k cos k phi + b_k sin k phi from the n samples (their discrete Fourier terms)
    a = 2.0 / n * (np.cos(np.outer(ks, phi)) @ error)
    b = 2.0 / n * (np.sin(np.outer(ks, phi)) @ error)
    seen_by_pixel = np.sinc(ks * float(footprint_px[0]) / n) * np.sinc(ks * float(footprint_px[1]) / n)
    a, b = a * seen_by_pixel, b * seen_by_pixel
    table_phi = 2.0 * np.pi * np.arange(DRAWN_TABLE_SIZE) / DRAWN_TABLE_SIZE
    table = float(np.mean(error)) + a @ np.cos(np.outer(ks, table_phi)) + b @ np.sin(np.outer(ks, table_phi))
    return tuple(float(v) for v in table)


def drawn_error_at(table, phase_rad: np.ndarray) -> np.ndarray:
    """A :func:`drawn_phase_error` table (rad, over one period) at the phases *phase_rad* (periodic linear
    interpolation)."""
    values = np.asarray(table, dtype=np.float64)
    m = values.size
    grid = 2.0 * np.pi * np.arange(m) / m
    return np.interp(np.asarray(phase_rad, dtype=np.float64), grid, values, period=2.0 * np.pi)


def drawn_table(fringes, axis: str, periods: float, footprint_px: dict | None = None):
    """The phase error table of set (*axis*, *periods*) as the display draws it and a camera pixel of footprint
    ``footprint_px[axis]`` (display pixels, :func:`pixel_footprint_px`; none: a point) sees it
    (:func:`drawn_phase_error`), or None when the fringes (a :class:`~sofast_station.fringes.FringeSet`) do not
    say how they are drawn (``FringeSet.drawn``) or it does not repeat."""
    n = fringes.samples_per_period(axis, periods)
    if n is None:
        return None
    lut, floor_level, max_level = fringes.drawn[:3]
    footprint = tuple((footprint_px or {}).get(axis, (0.0, 0.0)))
    return drawn_phase_error(lut, floor_level, max_level, n, footprint)


#: A pixel's footprint is rounded to this many decimals of a display pixel (:func:`pixel_footprint_px`): the
#: table it picks is kept per footprint, and a hundredth of a display pixel moves no harmonic by 1e-3 of itself.
FOOTPRINT_DECIMALS = 2


#: Pixels whose neighbours' steps :func:`pixel_footprint_px` takes the median of, at most (a fixed stride beyond).
FOOTPRINT_SAMPLES = 20_000


def pixel_footprint_px(shape: tuple, idx: np.ndarray, ok: np.ndarray, positions_m: dict, display_px: dict,
                       lengths_m: dict) -> dict:
    """The camera pixels' footprint on the screen along each fringe axis, display pixels.

    A pixel's footprint is the image of its square on the screen, a parallelogram whose edges are the
    screen position's steps from one pixel to the next along the image's columns and rows. Per axis a,
    ``(|du_a / d column|, |du_a / d row|)`` in display pixels: the median over pixels with trusted positions
    and a trusted neighbour (robust to the facet's slope errors and to the odd wrong position; at most
    :data:`FOOTPRINT_SAMPLES` pixels in a fixed stride: 20 ms at 1600 x 1200 where every pixel gave 490), rounded to
    :data:`FOOTPRINT_DECIMALS`.

    Parameters
    ----------
    shape : (rows, columns)
        The camera image's.
    idx : (M,) int array
        Flat image indices of the pixels, increasing.
    ok : (M,) bool array
        Pixels with trusted positions.
    positions_m : dict
        ``{"x": (M,), "y": (M,)}`` screen positions, metres.
    display_px, lengths_m : dict
        Per axis, the display's pixels across the screen and the screen's length, metres.

    Returns
    -------
    dict
        ``{"x": (a, b), "y": (a, b)}``, display pixels ((0, 0) for an axis without two neighbouring pixels).
    """
    width = shape[1]
    trusted = np.flatnonzero(ok)
    trusted = trusted[::max(1, trusted.size // FOOTPRINT_SAMPLES)]
    pairs = []
    for step in (1, width):                                   # the next column, the next row
        target = idx[trusted] + step
        at = np.minimum(np.searchsorted(idx, target), idx.size - 1)
        good = (idx[at] == target) & ok[at]
        if step == 1:
            good &= idx[trusted] % width != width - 1          # not the next row's first pixel
        pairs.append((trusted[good], at[good]))
    out = {}
    for axis in ("x", "y"):
        scale = display_px[axis] / lengths_m[axis]
        steps = []
        for i, j in pairs:
            d = np.abs(positions_m[axis][j] - positions_m[axis][i]) * scale
            steps.append(round(float(np.median(d)), FOOTPRINT_DECIMALS) if d.size else 0.0)
        out[axis] = tuple(steps)
    return out


def drawn_error_slope_at(table, phase_rad: np.ndarray) -> np.ndarray:
    """The derivative de/dphi (dimensionless) of a :func:`drawn_phase_error` table at the phases *phase_rad*
    (the table's periodic central differences, interpolated as :func:`drawn_error_at`)."""
    values = np.asarray(table, dtype=np.float64)
    slope = (np.roll(values, -1) - np.roll(values, 1)) * (values.size / (4.0 * np.pi))
    return drawn_error_at(slope, phase_rad)


def drawn_gain(fringes, axis: str, position_m: np.ndarray, length_m: float,
               footprint_px: dict | None = None) -> np.ndarray | None:
    """How much a phase error of the finest set of *axis* moves the corrected screen position, per the
    uncorrected move: ``1 - e'(phi)`` at each position (metres along the screen of *length_m*), or None when
    the fringes do not say how they are drawn (``FringeSet.drawn``). *footprint_px*: the camera pixels'
    footprint the correction used (``Phases.footprint_px``, :func:`pixel_footprint_px`).

    The analysis takes the drawn fringes' known error e(phi) off each pixel's phase
    (:func:`~.pipeline.corrected_positions`), so a phase error d of the capture (noise, a frame brighter than
    the others) is corrected by e(phi + d) - e(phi) too: the position moves by (1 - e'(phi)) d. Over a period
    e' averages to 0, so the gain's mean square is 1 + mean(e'^2): a few per cent on the stations' displays.
    (The part of the correction the period sets measure, a response not quite linearised, is left out: its
    coefficients are not kept, and it is a tenth of the drawn part on a calibrated display.)"""
    periods = getattr(fringes, f"periods_{axis}")[-1]
    table = drawn_table(fringes, axis, periods, footprint_px)
    if table is None:
        return None
    phase = 2.0 * np.pi * float(periods) * np.asarray(position_m, dtype=np.float64) / float(length_m)
    return 1.0 - drawn_error_slope_at(table, phase)


#: Harmonics of the phase (k phi) in the four-step phase error a static nonlinearity leaves: the response's
#: 3rd and 5th harmonics alias into the fundamental as a 4 phi error, the 7th and 9th as 8 phi.
PHASE_ERROR_HARMONICS = (4, 8)
#: Fewest pixels :func:`phase_error_between_periods` fits (a capture with fewer says nothing).
MIN_PHASE_ERROR_PIXELS = 500


@dataclass(frozen=True)
class PeriodPhaseError:
    """The four-step phase error a capture shows between its coarse and fine fringe sets.

    Attributes
    ----------
    max_rad, rms_rad : float
        Largest and RMS phase error over a period of the phase, rad (the noise's share of the fitted
        amplitude taken out).
    u_rad : float
        Standard uncertainty of ``max_rad`` from the fit's noise, rad.
    n_pixels : int
        Pixels (of every axis together) the fit used.
    harmonics : tuple of int
        The harmonics k of the phase fitted (:data:`PHASE_ERROR_HARMONICS`).
    coefficients : tuple of float
        e(phi) = sum_k a_k sin(k phi) + b_k cos(k phi): (a_k, b_k) per harmonic in *harmonics*' order, rad, as
        fitted (the noise's share of their power is taken out of ``max_rad`` and ``rms_rad`` only: the
        coefficients themselves are unbiased, which is what a correction needs).
    """

    max_rad: float
    rms_rad: float
    u_rad: float
    n_pixels: int
    harmonics: tuple = ()
    coefficients: tuple = ()

    def error_at(self, phase_rad: np.ndarray) -> np.ndarray:
        """e(phi), rad, at the (measured) four-step phases *phase_rad*: what the response added to them."""
        phi = np.asarray(phase_rad, dtype=np.float64)
        e = np.zeros(phi.shape)
        for k, a, b in zip(self.harmonics, self.coefficients[0::2], self.coefficients[1::2]):
            e += a * np.sin(k * phi) + b * np.cos(k * phi)
        return e


def _period_block(axis_sets: tuple, mask, n_axes: int, noise_dn: float, ks: np.ndarray) -> tuple | None:
    """One axis's rows of :func:`phase_error_between_periods`' fit: its own and the harmonic regressors with
    their derivatives by the fine and the coarse phase, the disagreement, both phases' noise variances and
    the period ratio; None when the ratio is not a whole number above 1."""
    phi_c, phi_f, b_c, b_f, p_c, p_f, *known = axis_sets
    r = float(p_f) / float(p_c)
    if r <= 1.0 or abs(r - round(r)) > 1e-9:
        return None
    # every step-th of the pixels in the mask, gathered straight from the images (not masked first)
    arrays = [np.asarray(v).ravel() for v in (phi_c, phi_f, b_c, b_f)]
    pick = (np.flatnonzero(np.asarray(mask, dtype=bool).ravel()) if mask is not None
            else np.arange(arrays[0].size))
    step = max(1, -(-pick.size * n_axes // MAX_NOISE_SAMPLES))
    phi_c, phi_f, b_c, b_f = (v[pick[::step]].astype(np.float64, copy=False) for v in arrays)
    # a known part of each set's error (the fringes' rounding as drawn: drawn_error_at), taken off the
    # disagreement: e_known_f(phi_f) - r e_known_c(phi_c)
    known = known[0] if known else None
    known_part = 0.0 if known is None else (drawn_error_at(known[1], phi_f) - r * drawn_error_at(known[0], phi_c))
    var_c = (noise_dn / (np.sqrt(2.0) * np.maximum(b_c, 1e-9))) ** 2
    var_f = (noise_dn / (np.sqrt(2.0) * np.maximum(b_f, 1e-9))) ** 2
    m = phi_c.size
    # The axis's own term, a constant (a phase offset between its sets), then the shared harmonics; with
    # each column's derivative by phi_f and by phi_c. (Each set's error at the phase's first harmonic, a
    # frame brighter or dimmer than the others of its set, is not fitted: over the few radians of
    # phase a small facet's coarse set sees, cos and sin phi_c are nearly the constant and the 4 phi_c
    # terms, and the fit came apart; left in, room light jittering by 0.2 % of white from frame to
    # frame adds about 0.7 mrad to the stated error, on the safe side.)
    own = [np.ones(m)]
    own_df = own_dc = [np.zeros(m)]
    kf, kc = ks[None, :] * phi_f[:, None], ks[None, :] * phi_c[:, None]
    harm = np.empty((m, 2 * ks.size))
    sin_f, cos_f, sin_c, cos_c = np.sin(kf), np.cos(kf), np.sin(kc), np.cos(kc)
    harm[:, 0::2] = sin_f - r * sin_c
    harm[:, 1::2] = cos_f - r * cos_c
    h_df, h_dc = np.empty_like(harm), np.empty_like(harm)
    h_df[:, 0::2], h_df[:, 1::2] = ks * cos_f, -ks * sin_f
    h_dc[:, 0::2], h_dc[:, 1::2] = -r * ks * cos_c, r * ks * sin_c
    y = np.angle(np.exp(1j * (phi_f - r * phi_c))) - known_part
    return (np.column_stack(own), np.column_stack(own_df), np.column_stack(own_dc), harm, h_df, h_dc,
            y, var_f, var_c, r)


def phase_error_between_periods(sets: list, noise_dn: float = 0.0, mask: list | None = None, pool=None
                                ) -> PeriodPhaseError | None:
    """The phase error of the four-step phases, measured from the disagreement of two period sets.

    A display (or camera) response that is not linear distorts every fringe alike, so the four-step phase
    of each set is off by the same function of the phase, e(phi), periodic with a quarter of a period
    (:data:`PHASE_ERROR_HARMONICS`: a sum of a_k sin k phi + b_k cos k phi). A pixel's coarse and fine
    phases see one screen point: with r = p_fine / p_coarse a whole number, phi_f - r phi_c (wrapped) is
    e(phi_f) - r e(phi_c) plus noise, whatever the response's shape. The a_k, b_k (and a constant per axis)
    are fitted to that over the pixels of every axis, and e's largest value and RMS over a period reported,
    with the noise's expected share of the fitted amplitude removed. No model of the response is assumed:
    the second harmonic's ratio (:func:`phase_error_from_harmonic`) holds for a power law only, and another
    shape can have a small second and a large third harmonic.

    The regressors sin k phi - r sin k phi_c are formed from the same noisy phases as the disagreement, so
    their noise and its noise are correlated: a least-squares fit would find a phase error of its own
    (about k r^2 sigma_c^2 / (r^2 / 2), 10 mrad at 5 DN of noise). Both first-order terms, the regressors'
    noise against the disagreement's and against itself (sigma = noise / (sqrt(2) b) per phase), are taken
    out of the normal equations.

    Parameters
    ----------
    sets : list of (phase_coarse, phase_fine, modulation_coarse, modulation_fine, p_coarse, p_fine[, known])
        Per axis: the wrapped phases (rad) and modulations (DN) of its coarsest and finest sets (the same
        pixels) and their period counts; optionally *known* = (coarse table, fine table), each set's error
        as drawn (:func:`drawn_phase_error`, or None), which differs between the sets and is taken off the
        disagreement before e is fitted: e is then what the response adds beyond the drawing.
    noise_dn : float
        Per-frame intensity noise, DN.
    mask : list of bool arrays or None
        Per axis, the pixels to use (those whose phases are trusted).
    pool : executor or None
        Forms the first half of the axes' regressors beside the rest (:func:`_map_halves`: the same
        values); None: all here.

    Returns
    -------
    PeriodPhaseError or None
        None when no axis has a whole-number period ratio above 1, too few pixels, or phases that do not
        spread enough to tell e from a constant.
    """
    ks = np.array(PHASE_ERROR_HARMONICS, dtype=np.float64)
    n_own = 1
    args = [(v, None if mask is None else mask[i], len(sets), noise_dn, ks) for i, v in enumerate(sets)]
    blocks = [b for b in _map_halves(pool, lambda a: _period_block(*a), args) if b is not None]
    if not blocks or sum(bl[6].size for bl in blocks) < MIN_PHASE_ERROR_PIXELS:
        return None
    n_axes = len(blocks)
    n_const = n_own * n_axes
    n = sum(bl[6].size for bl in blocks)
    x, d_f, d_c = (np.zeros((n, n_const + 2 * ks.size)) for _ in range(3))
    y, var_f, var_c, ratio = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    start = 0
    for j, (own, own_df, own_dc, harm, h_df, h_dc, yb, vf, vc, r) in enumerate(blocks):
        sl = slice(start, start + yb.size)
        cols = slice(n_own * j, n_own * (j + 1))
        x[sl, cols], d_f[sl, cols], d_c[sl, cols] = own, own_df, own_dc
        x[sl, n_const:], d_f[sl, n_const:], d_c[sl, n_const:] = harm, h_df, h_dc
        y[sl], var_f[sl], var_c[sl], ratio[sl] = yb, vf, vc, r
        start += yb.size
    # the regressors' noise: d_f n_f + d_c n_c; the disagreement's: n_f - r n_c
    nf = d_f * np.sqrt(var_f)[:, None]
    nc = d_c * np.sqrt(var_c)[:, None]
    cross = d_f * var_f[:, None] - (ratio * var_c)[:, None] * d_c
    # The normal equations over every pixel once; each round takes out the pixels it leaves out (a few: a
    # coarse phase that slipped a fringe), rather than forming them again over the pixels it keeps (when
    # most are left out, over those kept: a difference of two near-equal sums would lose its digits).
    def normal_equations(rows):
        xr, nfr, ncr = x[rows], nf[rows], nc[rows]
        return xr.T @ xr - nfr.T @ nfr - ncr.T @ ncr, xr.T @ y[rows] - cross[rows].sum(axis=0)

    xtx_all = x.T @ x - nf.T @ nf - nc.T @ nc
    xty_all = x.T @ y - cross.sum(axis=0)
    keep = np.ones(n, dtype=bool)
    for _ in range(3):               # a pixel whose coarse phase slipped a fringe: leave it out
        out = np.flatnonzero(~keep)
        if 2 * out.size > n:
            xtx, xty = normal_equations(np.flatnonzero(keep))
        else:
            xtx_out, xty_out = normal_equations(out)
            xtx, xty = xtx_all - xtx_out, xty_all - xty_out
        if np.linalg.cond(xtx) > 1e10:
            return None
        coef = np.linalg.solve(xtx, xty)
        res = y - x @ coef
        sigma = trimmed_std(res[keep])
        keep = np.abs(res) < TRIM_SIGMAS * max(sigma, 1e-9)
    cov = np.linalg.inv(xtx) * sigma ** 2
    harm = coef[n_const:]
    cov_h = cov[n_const:, n_const:]
    # The fitted coefficients' power holds the noise's (the trace of their covariance): take it out.
    power = float(harm @ harm)
    shrink = np.sqrt(max(power - float(np.trace(cov_h)), 0.0) / power) if power > 0 else 0.0
    phi = np.linspace(0.0, TWO_PI, 720, endpoint=False)
    basis = np.column_stack([f(k * phi) for k in PHASE_ERROR_HARMONICS for f in (np.sin, np.cos)])
    e = basis @ harm
    at = int(np.argmax(np.abs(e)))
    u_max = float(np.sqrt(basis[at] @ cov_h @ basis[at]))
    return PeriodPhaseError(max_rad=float(shrink * np.abs(e[at])), rms_rad=float(shrink * np.sqrt(np.mean(e * e))),
                            u_rad=u_max, n_pixels=int(keep.sum()), harmonics=tuple(int(k) for k in ks),
                            coefficients=tuple(float(c) for c in harm))


#: Brightness bins of each kind (equal counts, equal widths) over which :func:`noise_by_level` fits the
#: noise's growth.
NOISE_LEVEL_BINS = 12
#: Fewest residuals a brightness bin needs to count in that fit.
NOISE_LEVEL_MIN_SAMPLES = 200


def noise_by_level(residuals, level_dn: np.ndarray, frame_noise_dn: float,
                   bins: int = NOISE_LEVEL_BINS) -> tuple[float, float]:
    """The frame noise's variance as an affine function of the pixel's brightness, sigma^2 = a + b w.

    A camera's noise grows with the light a pixel gathers (shot noise: variance in proportion to the
    signal, on top of the read noise and the rounding), so one noise figure for the whole facet over-states
    the noise of its dim pixels and under-states that of its bright ones. Dim pixels are mostly at the
    facet's edges (vignetting, and pixels the edge only partly covers), where they weigh most in the fits'
    curvature and twist. Each consistency residual I_0 + I_2 - I_1 - I_3 has variance 4 sigma^2 at its
    pixel (the fringe's own term cancels), so the residuals, binned by brightness *level_dn* (white - dark,
    DN, the same pixels as each residual array; *bins* bins of equal counts and *bins* of equal widths),
    give a variance per bin (the mean square of the residuals within 4.5 of the capture's standard
    deviations, so the few spoiled pixels do not count), and a line weighted by each bin's count over its
    variance squared gives a and b.

    The line is then scaled so that its mean over the pixels is *frame_noise_dn* squared: the overall
    level stays the capture's own estimate (:func:`intensity_noise_dn`), and only its spread over the
    pixels comes from here. b = 0 (one level for every pixel) when fewer than three bins have
    :data:`NOISE_LEVEL_MIN_SAMPLES` residuals, when their brightness does not spread, or when the fitted
    noise does not grow with brightness.

    Returns
    -------
    (a, b) : DN^2 and DN (sigma^2 in DN^2 for w in DN; :func:`noise_at_level` evaluates it)
    """
    flat = frame_noise_dn ** 2
    level_dn = np.asarray(level_dn, dtype=np.float64).ravel()
    sets = [np.asarray(r).ravel() for r in residuals]
    if not sets or any(r.size != level_dn.size for r in sets) or level_dn.size == 0:
        return flat, 0.0
    stride = max(1, -(-level_dn.size * len(sets) // MAX_NOISE_SAMPLES))
    w_s = level_dn[::stride]
    finite = np.isfinite(w_s)
    if np.count_nonzero(finite) * len(sets) < 3 * NOISE_LEVEL_MIN_SAMPLES or flat <= 0:
        return flat, 0.0
    # Bins of equal counts (where most pixels are) and of equal width (the few dim ones at the edges,
    # which decide the line's slope when the facet's inside is evenly lit).
    steps = np.linspace(0.0, 1.0, bins + 1)
    wf = w_s[finite]
    edges = np.unique(np.concatenate([np.quantile(wf, steps), wf.min() + steps * (wf.max() - wf.min())]))
    n_bins = max(edges.size - 1, 1)
    which = np.clip(np.searchsorted(edges, np.where(finite, w_s, edges[0]), side="right") - 1, 0, n_bins - 1)
    # Each bin's variance from the residuals within 4.5 of the capture's standard deviations (a spoiled
    # pixel is far beyond; a Gaussian loses 1e-4 of its variance there), summed over the sets.
    limit = (2.0 * TRIM_SIGMAS * np.sqrt(flat)) ** 2
    counts, sums, level_sums = np.zeros(n_bins), np.zeros(n_bins), np.zeros(n_bins)
    for r in sets:
        r2 = np.square(r[::stride], dtype=np.float64)
        keep = finite & (r2 <= limit)
        bin_of = which[keep]
        counts += np.bincount(bin_of, minlength=n_bins)
        sums += np.bincount(bin_of, weights=r2[keep], minlength=n_bins)
        level_sums += np.bincount(bin_of, weights=w_s[keep], minlength=n_bins)
    use = counts >= NOISE_LEVEL_MIN_SAMPLES
    levels = level_sums[use] / counts[use]
    variances = sums[use] / counts[use] / 4.0
    counts = counts[use]
    if levels.size < 3 or np.ptp(levels) <= 0 or np.any(variances <= 0):
        return flat, 0.0
    x, v, weight = levels, variances, counts / np.square(variances)
    xm = float(np.sum(weight * x) / np.sum(weight))
    vm = float(np.sum(weight * v) / np.sum(weight))
    b = float(np.sum(weight * (x - xm) * (v - vm)) / np.sum(weight * (x - xm) ** 2))
    if not np.isfinite(b) or b <= 0:
        return flat, 0.0
    a = vm - b * xm
    mean_var = float(np.mean(np.maximum(a + b * wf, QUANTISATION_NOISE_DN ** 2)))
    scale = flat / mean_var if mean_var > 0 else 1.0
    return float(a * scale), float(b * scale)


def noise_at_level(model: tuple[float, float], level_dn: np.ndarray) -> np.ndarray:
    """Each pixel's frame noise (DN, rounding included) at its brightness *level_dn* (white - dark, DN)
    by the line (a, b) of :func:`noise_by_level`; never below the rounding's 1/sqrt(12) DN."""
    a, b = model
    var = a + b * np.asarray(level_dn, dtype=np.float64)
    return np.sqrt(np.maximum(var, QUANTISATION_NOISE_DN ** 2))


def _map_halves(pool, fn, items) -> list:
    """``[fn(x) for x in items]`` with the first half of the items done on *pool* (an executor, or None)
    beside the rest: each item's arithmetic is the same on any thread, so the same values."""
    items = list(items)
    half = len(items) // 2 if pool is not None else 0
    first = pool.submit(lambda: [fn(x) for x in items[:half]]) if half else None
    rest = [fn(x) for x in items[half:]]
    return (first.result() if first is not None else []) + rest


def _block_lstsq(samples: list, first_blocks: dict | None = None) -> np.ndarray:
    """:func:`_robust_lstsq` of the joint fit without forming its (mostly zero) design matrix.

    *samples*: per set (own rows (m, n_k), shared rows (4, n_k), residuals (n_k,)). The unknowns are every
    set's own coefficients then the four shared ones; the normal equations are assembled block by block
    from each set's own and shared rows (einsum's loops, no BLAS), refitted without residuals beyond 5
    trimmed standard deviations like :func:`_robust_lstsq`.

    The first round keeps every sample, so each set's sums there do not depend on the other sets:
    *first_blocks* (a dict the caller keeps while its samples live) keeps them between fits of different
    groups of the same sets (the same sums, so the same bits).
    """
    m = samples[0][0].shape[0]
    n_own = m * len(samples)
    keeps = [np.ones(r.size, dtype=bool) for _, _, r in samples]
    coef = np.zeros(n_own + 4)
    for round_ in range(3):
        first = round_ == 0
        gram = np.zeros((n_own + 4, n_own + 4))
        rhs = np.zeros(n_own + 4)
        for j, ((own, shared, r), keep) in enumerate(zip(samples, keeps)):
            a = slice(m * j, m * (j + 1))
            blocks = None if first_blocks is None or not first else first_blocks.get(id(r))
            if blocks is None:
                # (row-major copies: numpy's boolean indexing along the second axis returns column-major
                # arrays, on which einsum's sums run several times slower)
                o, sh, y = ((own, shared, r) if keep.all() else
                            (np.ascontiguousarray(own[:, keep]), np.ascontiguousarray(shared[:, keep]), r[keep]))
                blocks = (np.einsum("in,jn->ij", o, o, optimize=False), np.einsum("in,jn->ij", o, sh, optimize=False),
                          np.einsum("in,jn->ij", sh, sh, optimize=False), np.einsum("in,n->i", o, y, optimize=False),
                          np.einsum("in,n->i", sh, y, optimize=False))
                if first and first_blocks is not None:
                    first_blocks[id(r)] = blocks
            oo, cross, ss, oy, sy = blocks
            gram[a, a] = oo
            gram[a, n_own:] = cross
            gram[n_own:, a] = cross.T
            gram[n_own:, n_own:] += ss
            rhs[a] = oy
            rhs[n_own:] += sy
        coef = np.linalg.solve(gram, rhs)
        res = [minus_models(r, own, coef[m * j:m * (j + 1)], shared, coef[n_own:])
               for j, (own, shared, r) in enumerate(samples)]
        all_res = np.concatenate(res)
        limit = 5.0 * max(trimmed_std(all_res), 0.5)
        new_keeps = [np.abs(rr) <= limit for rr in res]
        if all(np.array_equal(a, b) for a, b in zip(new_keeps, keeps)) or \
                sum(int(k.sum()) for k in new_keeps) < (n_own + 4) * 3:
            break
        keeps = new_keeps
    return coef


def _robust_lstsq(design: np.ndarray, r: np.ndarray, rounds: int = 3, stride: bool = True) -> np.ndarray:
    """Least squares of r on the rows of *design* (k, N), refitted without residuals beyond 5 trimmed
    standard deviations (the pixels a half-drawn frame spoils), on a fixed stride of the points."""
    d, y = (design[:, :: max(1, -(-r.size // MAX_NOISE_SAMPLES))], _stride(r)) if stride else (design, r)
    keep = np.ones(y.size, dtype=bool)
    coef = np.zeros(design.shape[0])
    for _ in range(rounds):
        dk, yk = np.ascontiguousarray(d[:, keep]), y[keep]        # (row-major: see _block_lstsq)
        # Normal equations by einsum's own loops: no BLAS call sees pixel-length data (determinism).
        gram = np.einsum("in,jn->ij", dk, dk, optimize=False)
        coef = np.linalg.solve(gram, np.einsum("in,n->i", dk, yk, optimize=False))
        res = minus_models(y, d, coef)
        new_keep = np.abs(res) <= 5.0 * max(trimmed_std(res), 0.5)
        if np.array_equal(new_keep, keep) or new_keep.sum() < design.shape[0] * 3:
            break
        keep = new_keep
    return coef


@dataclass(frozen=True)
class UnwrapResult:
    """Screen positions along one axis.

    Attributes
    ----------
    position_m : array
        Position u along the axis from the left (x) or bottom (y) edge, metres, in [0, L); NaN where
        invalid.
    valid : bool array
    coarse_out_of_range, disagreements, edge_guard : int
        Pixels dropped because the coarsest position fell outside [0, L), because two successive
        positions disagreed by more than a quarter of the finer period, or because they lay within the
        guard band of a screen edge.
    """

    position_m: np.ndarray
    valid: np.ndarray
    coarse_out_of_range: int
    disagreements: int
    edge_guard: int


def unwrap_positions(phases: list[np.ndarray] | tuple[np.ndarray, ...], periods, length_m: float,
                     position_sigma_m: np.ndarray | float = 0.0, guard_sigmas: float = 4.0) -> UnwrapResult:
    """Temporal unwrapping, coarse to fine, into screen positions (docs/conventions.md#unwrapping).

    Parameters
    ----------
    phases : sequence of arrays
        Wrapped phases in [0, 2 pi), one per period count, coarse first.
    periods : sequence of float
        Increasing period counts p_1 < p_2 < ... (cycles across ``length_m``).
    length_m : float
        Active extent L along the axis, metres.
    position_sigma_m : array or float
        Position noise of the finest phase per pixel (metres); sets the edge guard band when every
        period is a whole number.
    guard_sigmas : float
        Guard band half-width in units of ``position_sigma_m`` (at least 4: docs/conventions.md#unwrapping).

    Returns
    -------
    UnwrapResult
    """
    periods = [float(p) for p in periods]
    if len(phases) != len(periods) or not periods:
        raise ValueError(f"need one phase per period, got {len(phases)} phases for periods {periods}")
    if any(b <= a for a, b in zip(periods, periods[1:])) or periods[0] <= 0:
        raise ValueError(f"periods must be positive and increasing, got {periods}")
    if not (np.isfinite(length_m) and length_m > 0):
        raise ValueError(f"length_m must be a positive length, got {length_m}")
    if guard_sigmas < 4.0:
        raise ValueError(f"guard_sigmas must be at least 4 (docs/conventions.md#unwrapping), got {guard_sigmas}")
    big_l = float(length_m)
    whole = all(abs(p - round(p)) < 1e-12 for p in periods)
    shape = np.shape(phases[0])
    sigma = np.asarray(position_sigma_m, dtype=np.float64)
    if sigma.ndim > 0:
        sigma = np.broadcast_to(sigma, shape)
    u, valid, coarse_bad, disagree, near_edge = unwrap(phases, periods, big_l, whole, float(guard_sigmas),
                                                       sigma if sigma.ndim > 0 else float(sigma))
    return UnwrapResult(u.reshape(shape), valid.reshape(shape), coarse_bad, disagree, near_edge)


def position_sigma_m(modulation_dn: np.ndarray, noise_dn: float, finest_periods: float,
                     length_m: float) -> np.ndarray:
    """Position noise (metres) of the finest phase: L / (2 pi p) * sigma / (sqrt(2) b).

    With four steps, sin and cos estimates each carry noise sqrt(2) sigma against an amplitude 2b, so
    the phase noise is sigma / (sqrt(2) b) radians.
    """
    b = np.maximum(modulation_dn, 1e-9, dtype=np.float64)
    scale = length_m / (TWO_PI * finest_periods) * noise_dn
    if np.ndim(b) == 0:
        return scale / (np.sqrt(2.0) * b)
    b *= np.sqrt(2.0)                           # in place: the same values as scale / (sqrt(2) b)
    return np.divide(scale, b, out=b)
